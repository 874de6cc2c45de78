"""`rasterize()`: the one public entry point, and the choice of backend behind it.

Every backend answers the same interface (backend.py) and contract (shapes, constants,
gradients, the projection). This module does, once and for all of them: validate the inputs;
replace zero quaternions by the identity; answer an empty scene (no Gaussians) or a zero-area
image itself, so no backend ever launches a kernel for one (gsplat would kill the process);
pick the backend (`auto`: gsplat for CUDA tensors when it works, else the C++ kernels for CPU
tensors, else the torch reference; the choice is logged once, a fallback warned once); blend
the background, turn accumulated depth into expected depth, and assemble `info`.
"""

from __future__ import annotations

import importlib
import logging
import warnings

import torch

from . import constants as K_
from .backend import SplatBackend, blank_images, track_means2d
from .types import BackendOutput, BackendUnavailable, Projection, RenderOptions, RenderRequest, RenderStats
from .validation import check_inputs

log = logging.getLogger(__name__)

# The backends, by name: each module holds one object `BACKEND` answering `SplatBackend`.
# A new backend is a new module and one line here.
_BACKEND_MODULES = {"torch": "torch_reference", "cpu": "cpu_backend", "cuda": "cuda_backend"}
BACKENDS = ("auto", *_BACKEND_MODULES)
DEPTH_MODES = ("expected", "accumulated")

_logged_choices: set[tuple[str, str]] = set()
_warned: set[str] = set()
_failures: dict[str, BackendUnavailable] = {}  # backends that failed at render time, by name


def backend_impl(name: str) -> SplatBackend:
    """The backend object registered under `name` (imported on first use)."""
    return importlib.import_module(f".{_BACKEND_MODULES[name]}", __package__).BACKEND


def _warn_once(key: str, message: str) -> None:
    if key in _warned:
        return
    _warned.add(key)
    warnings.warn(message, RuntimeWarning, stacklevel=4)
    log.warning(message)


def backend_status(name: str) -> str | None:
    """None if backend `name` can run here (may build the CPU kernels), else why not."""
    if name in _failures:
        return str(_failures[name])
    try:
        backend_impl(name).check()
    except BackendUnavailable as exc:
        return str(exc)
    return None


def cpu_backend_status() -> str | None:
    """None if the C++ kernels load (building them on first call), else why not."""
    return backend_status("cpu")


def cuda_backend_status() -> str | None:
    """None if gsplat imports (its kernels compile on the first render), else why not."""
    return backend_status("cuda")


def available_backends() -> list[str]:
    """The concrete backends usable in this process (may build the CPU kernels)."""
    return [name for name in _BACKEND_MODULES if name == "torch" or backend_status(name) is None]


def _log_choice(device: str, backend: str, why: str) -> None:
    key = (device, backend)
    if key not in _logged_choices:
        _logged_choices.add(key)
        log.info("splat backend for %s tensors: %s (%s)", device, backend, why)


def resolve_backend(backend: str, device: torch.device) -> str:
    """The concrete backend `rasterize` will use for tensors on `device`."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; choose one of {', '.join(BACKENDS)}")
    if backend != "auto":
        impl = backend_impl(backend)
        if impl.device_type is not None and device.type != impl.device_type:
            raise ValueError(
                f"backend={backend!r} needs {impl.device_type.upper()} tensors, got tensors on {device}"
            )
        impl.check()  # raises BackendUnavailable naming the reason (a named backend never falls back)
        return backend
    for name in _BACKEND_MODULES:
        impl = backend_impl(name)
        if impl.device_type != device.type:
            continue
        status = backend_status(name)
        if status is None:
            _log_choice(device.type, name, impl.description)
            return name
        _warn_once(
            name,
            f"{impl.description} unavailable ({status}); rendering {device.type.upper()} tensors "
            "with the slow torch reference",
        )
        _log_choice(device.type, "torch", status)
        return "torch"
    _log_choice(device.type, "torch", "no dedicated backend for this device")
    return "torch"


def sanitize_quats(quats: torch.Tensor) -> torch.Tensor:
    """Quaternions whose every component is below QUAT_NORM_EPS in magnitude (a zero one) ->
    the identity (1, 0, 0, 0); the others are returned untouched.

    Applied before any backend sees them: gsplat would turn them into NaN covariances (its
    squared norm underflows), ours into a degenerate matrix, so one documented behaviour needs
    one place. The replaced rows get a zero gradient. One cheap reduction in the common case
    where nothing needs replacing (one device sync on CUDA)."""
    if quats.numel() == 0:
        return quats
    largest = quats.detach().abs().amax(dim=-1)
    if not bool(largest.amin() < K_.QUAT_NORM_EPS):
        return quats
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=quats.dtype, device=quats.device)
    return torch.where((largest < K_.QUAT_NORM_EPS)[:, None], identity, quats)


def _empty_render(request: RenderRequest) -> BackendOutput:
    """No Gaussians or no pixels: nothing to draw, no backend called. Outputs and the all-culled
    projection stay in the autograd graph (zero gradients, means2d .grad/.absgrad set)."""
    means = request.means
    n, dtype, device = means.shape[0], means.dtype, means.device
    projection = Projection(
        means2d=means[:, :2] * 0.0,
        conics=torch.zeros((n, 3), dtype=dtype, device=device),
        depths=torch.zeros((n,), dtype=dtype, device=device),
        opacities=request.opacities * 0.0,
        radii=torch.zeros((n, 2), dtype=torch.int32, device=device),
        bbox=torch.tensor([0, -1, 0, -1], dtype=torch.int32, device=device).repeat(n, 1),
        visible=torch.zeros((n,), dtype=torch.bool, device=device),
    )
    holder = track_means2d(projection.means2d)
    image, alpha, depth = blank_images(request, projection, holder, dtype)
    return BackendOutput(image, alpha, depth, projection, RenderStats(n_intersections=0))


def _render(chosen: str, request: RenderRequest, *, explicit: bool) -> tuple[str, BackendOutput]:
    """Render with `chosen`; under `auto`, a backend that fails at render time (gsplat's build)
    is remembered as unavailable and the torch reference renders instead."""
    try:
        return chosen, backend_impl(chosen).render(request)
    except BackendUnavailable as exc:
        if explicit or chosen == "torch":
            raise
        _failures[chosen] = exc
        device = request.means.device.type
        _warn_once(
            chosen,
            f"{backend_impl(chosen).description} is not usable ({exc}); rendering {device.upper()} "
            "tensors with the slow torch reference",
        )
        _log_choice(device, "torch", str(exc))
        return "torch", backend_impl("torch").render(request)


def rasterize(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    background: torch.Tensor | float | None = None,
    backend: str = "auto",
    *,
    near_plane: float = K_.NEAR_PLANE,
    far_plane: float = K_.FAR_PLANE,
    eps2d: float = K_.LOW_PASS_EPS2D,
    antialiased: bool = False,
    radius_clip: float = 0.0,
    render_depth: bool = False,
    depth_mode: str = "expected",
    check_inputs_finite: bool = True,
    max_intersections: int = K_.MAX_INTERSECTIONS_PER_CHUNK,
) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """Render 3D Gaussians into one pinhole camera, differentiably.

    Args:
        means: [N, 3] centres in world space (metres).
        quats: [N, 4] rotations, wxyz, any norm (normalised inside; one whose components are
            all below 1e-12 in magnitude, e.g. zero, is the identity, with a zero gradient).
        scales: [N, 3] standard deviations along the rotated axes, activated (>= 0).
        opacities: [N] activated opacities (in [0, 1]).
        colors: [N, C] any number of channels (RGB, features ...), blended as given.
        viewmat: [4, 4] world-to-camera matrix, OpenCV axes (x right, y down, z forward).
        K: [3, 3] pinhole intrinsics [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in pixels.
        width, height: image size in pixels (0 gives an empty image).
        background: [C] (or a scalar) colour behind the Gaussians; default black.
        backend: "auto", "cpu" (C++/OpenMP), "cuda" (gsplat) or "torch" (reference).
        near_plane, far_plane: depth culling of the centres, metres.
        eps2d: low-pass dilation added to every 2D covariance (pixels^2).
        antialiased: scale opacities by sqrt(det(S) / det(S + eps2d I)) (Mip-Splatting),
            like gsplat's rasterize_mode="antialiased".
        radius_clip: drop Gaussians whose screen radius is <= this many pixels.
        render_depth: also render camera-z depth into ``info["depth"]`` ([H, W, 1]).
        depth_mode: "expected" (sum w z / sum w, like gsplat "ED") or "accumulated"
            (sum w z, gsplat "D").
        check_inputs_finite: check every input for NaN/inf and camera sanity (one pass).
        max_intersections: tile intersections rasterised per chunk by the cpu backend
            (bounds its memory; more only costs extra passes).

    Returns:
        image [H, W, C], alpha [H, W, 1], and ``info`` with:
        ``backend`` (the one used), ``means2d`` ([N, 2] projected centres, differentiable;
        after ``backward()`` its ``.grad`` holds dL/dmeans2d and ``.absgrad`` the sum over
        pixels of |dL/dmeans2d| (AbsGS), both accumulating like ``.grad``; in pixels),
        ``radii`` ([N, 2] int32 screen radius in x and y, 0 = culled), ``visible`` ([N] bool,
        radii > 0: gsplat's culling rules, docs/SPLAT.md), ``depths`` ([N] camera z),
        ``conics`` ([N, 3]), ``opacities`` ([N] effective), ``n_intersections`` (tile pairs
        the backend processed), ``n_gaussians``, ``width``, ``height``, ``tile_size``,
        ``stats`` (backend-specific stage timings, filled further by backward) and ``depth``
        when asked.

    An empty scene (no Gaussians, or every one culled) or a zero-area image renders the
    background (alpha 0) on every backend, never launching a kernel for nothing.

    Gradients flow to means, quats, scales, opacities, colors and background (not to
    viewmat or K).
    """
    if depth_mode not in DEPTH_MODES:
        raise ValueError(f"depth_mode must be one of {DEPTH_MODES}, got {depth_mode!r}")
    if not 0 < near_plane < far_plane:
        raise ValueError(
            f"need 0 < near_plane < far_plane, got near_plane={near_plane}, far_plane={far_plane}"
        )
    if not eps2d >= 0 or not radius_clip >= 0:
        raise ValueError(f"eps2d and radius_clip must be >= 0, got eps2d={eps2d}, radius_clip={radius_clip}")
    if int(max_intersections) < 1:
        raise ValueError(f"max_intersections must be >= 1, got {max_intersections}")
    if isinstance(background, (int, float)) and background == 0:
        background = None  # black: blending it adds 0 to every pixel, forward and backward
    if not isinstance(background, torch.Tensor) and background is not None:
        background = torch.as_tensor(background, dtype=colors.dtype, device=colors.device)
    check_inputs(
        means,
        quats,
        scales,
        opacities,
        colors,
        viewmat,
        K,
        width,
        height,
        background,
        finite=check_inputs_finite,
    )
    chosen = resolve_backend(backend, means.device)
    request = RenderRequest(
        means=means,
        quats=sanitize_quats(quats),
        scales=scales,
        opacities=opacities,
        colors=colors,
        viewmat=viewmat,
        K=K,
        width=width,
        height=height,
        options=RenderOptions(
            near_plane=float(near_plane),
            far_plane=float(far_plane),
            eps2d=float(eps2d),
            radius_clip=float(radius_clip),
            antialiased=bool(antialiased),
            render_depth=bool(render_depth),
            max_intersections=int(max_intersections),
        ),
    )
    n = means.shape[0]
    if n == 0 or width == 0 or height == 0:
        out = _empty_render(request)
    else:
        chosen, out = _render(chosen, request, explicit=backend != "auto")

    dtype = means.dtype
    image, alpha, depth = out.image, out.alpha, out.depth
    if depth is not None and depth_mode == "expected":
        depth = depth / alpha.clamp_min(K_.DEPTH_ALPHA_EPS)
    if background is not None:
        image = image + (1.0 - alpha) * background.to(dtype)
    proj = out.projection
    info = {
        "backend": chosen,
        "means2d": proj.means2d,
        "radii": proj.radii,
        "visible": proj.visible,
        "depths": proj.depths,
        "conics": proj.conics,
        "opacities": proj.opacities,
        "n_intersections": out.stats.n_intersections,
        "n_gaussians": n,
        "width": width,
        "height": height,
        "tile_size": K_.TILE_SIZE,
        "stats": out.stats.stages,
    }
    if depth is not None:
        info["depth"] = depth
    return image, alpha, info
