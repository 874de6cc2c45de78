"""`rasterize()`: the one public entry point, and the choice of backend behind it.

Every backend answers the same contract (shapes, constants, gradients, the `info` dict);
this module validates the inputs once, picks the backend (`auto`: gsplat for CUDA tensors
when it works, else the C++ kernels, else the torch reference; the choice is logged once),
adds the optional depth channel and the background, and assembles `info`.
"""

from __future__ import annotations

import logging
import warnings

import torch

from . import constants as K_
from . import torch_reference
from .build import ExtensionUnavailable, load_kernels
from .validation import check_inputs

log = logging.getLogger(__name__)

BACKENDS = ("auto", "torch", "cpu", "cuda")
DEPTH_MODES = ("expected", "accumulated")

_logged_choices: set[tuple[str, str]] = set()
_warned: set[str] = set()
_cuda_failure: Exception | None = None


class _AbsGradHolder:
    """Lets a backend's backward add AbsGS statistics to ``info["means2d"].absgrad``."""

    def __init__(self, tensor: torch.Tensor):
        self.tensor = tensor

    def add_absgrad(self, index: torch.Tensor | None, values: torch.Tensor) -> None:
        t = self.tensor
        current = getattr(t, "absgrad", None)
        if current is None:
            current = torch.zeros(t.shape, dtype=t.dtype, device=t.device)
        values = values.to(dtype=t.dtype, device=t.device)
        if index is None:
            current = current + values
        else:
            current = current.index_add(0, index, values)
        t.absgrad = current


def _warn_once(key: str, message: str) -> None:
    if key in _warned:
        return
    _warned.add(key)
    warnings.warn(message, RuntimeWarning, stacklevel=3)
    log.warning(message)


def cpu_backend_status() -> str | None:
    """None if the C++ kernels load (building them on first call), else why not."""
    try:
        load_kernels()
    except ExtensionUnavailable as exc:
        return str(exc)
    return None


def cuda_backend_status() -> str | None:
    """None if gsplat imports (its kernels compile on the first render), else why not."""
    if not torch.cuda.is_available():
        return "no CUDA device"
    if _cuda_failure is not None:
        return str(_cuda_failure)
    from .cuda_backend import GsplatUnavailable, import_gsplat

    try:
        import_gsplat()
    except GsplatUnavailable as exc:
        return str(exc)
    return None


def available_backends() -> list[str]:
    """The concrete backends usable in this process (may build the CPU kernels)."""
    out = ["torch"]
    if cpu_backend_status() is None:
        out.append("cpu")
    if cuda_backend_status() is None:
        out.append("cuda")
    return out


def _log_choice(device: str, backend: str, why: str) -> None:
    key = (device, backend)
    if key not in _logged_choices:
        _logged_choices.add(key)
        log.info("splat backend for %s tensors: %s (%s)", device, backend, why)


def resolve_backend(backend: str, device: torch.device) -> str:
    """The concrete backend `rasterize` will use for tensors on `device`."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; choose one of {', '.join(BACKENDS)}")
    if backend == "cuda":
        if device.type != "cuda":
            raise ValueError(f"backend='cuda' needs CUDA tensors, got tensors on {device}")
        return "cuda"
    if backend == "cpu":
        if device.type != "cpu":
            raise ValueError(f"backend='cpu' needs CPU tensors, got tensors on {device}")
        load_kernels()  # raises ExtensionUnavailable, naming the reason (and the build log)
        return "cpu"
    if backend == "torch":
        return "torch"
    if device.type == "cuda":
        status = cuda_backend_status()
        if status is None:
            _log_choice("cuda", "cuda", "gsplat")
            return "cuda"
        _warn_once(
            "cuda", f"gsplat is not usable ({status}); rendering CUDA tensors with the slow torch reference"
        )
        _log_choice("cuda", "torch", status)
        return "torch"
    if device.type == "cpu":
        status = cpu_backend_status()
        if status is None:
            _log_choice("cpu", "cpu", "C++/OpenMP kernels")
            return "cpu"
        _warn_once(
            "cpu", f"C++ splat kernels unavailable ({status}); falling back to the slow torch reference"
        )
        _log_choice("cpu", "torch", status)
        return "torch"
    _log_choice(device.type, "torch", "no dedicated backend for this device")
    return "torch"


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
        quats: [N, 4] rotations, wxyz, any norm (normalised inside; a zero quaternion is the
            identity).
        scales: [N, 3] standard deviations along the rotated axes, activated (>= 0).
        opacities: [N] activated opacities (in [0, 1]).
        colors: [N, C] any number of channels (RGB, features ...), blended as given.
        viewmat: [4, 4] world-to-camera matrix, OpenCV axes (x right, y down, z forward).
        K: [3, 3] pinhole intrinsics [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in pixels.
        width, height: image size in pixels.
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
        ``radii`` ([N, 2] int32 screen radius in x and y, 0 = culled), ``visible`` ([N] bool),
        ``depths`` ([N] camera z), ``conics`` ([N, 3]), ``opacities`` ([N] effective),
        ``n_intersections``, ``width``, ``height``, ``tile_size`` and ``depth`` when asked.

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
    options = dict(
        near_plane=near_plane,
        far_plane=far_plane,
        eps2d=eps2d,
        radius_clip=radius_clip,
        antialiased=antialiased,
    )
    if chosen == "cuda":
        try:
            return _rasterize_cuda(
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
                render_depth,
                depth_mode,
                options,
                explicit=backend == "cuda",
            )
        except _FallBack:
            chosen = "torch"

    n = means.shape[0]
    if chosen == "cpu":
        from . import cpu_backend as impl

        options["max_intersections"] = max_intersections
        dtype = means.dtype
        f32 = (means.float(), quats.float(), scales.float(), opacities.float(), colors.float())
        means_, quats_, scales_, opacities_, colors_ = f32
    else:
        impl = torch_reference
        dtype = means.dtype
        means_, quats_, scales_, opacities_, colors_ = means, quats, scales, opacities, colors

    # Depth planes in the precision of the (working) inputs, so a centre placed exactly on the
    # near plane in float32 is kept, as in gsplat.
    for key in ("near_plane", "far_plane"):
        options[key] = float(torch.tensor(options[key], dtype=means_.dtype))
    proj = impl.project(means_, quats_, scales_, opacities_, viewmat, K, width, height, **options)
    means2d = proj.means2d
    holder = None
    if means2d.requires_grad:
        means2d.retain_grad()
        holder = _AbsGradHolder(means2d)
    render_colors = colors_
    if render_depth:
        render_colors = torch.cat([colors_, proj.depths[:, None].to(colors_.dtype)], dim=1)
    if chosen == "cpu":
        image, alpha = impl.rasterize(proj, render_colors, width, height, holder=holder, **options)
    else:
        image, alpha = impl.rasterize(proj, render_colors, width, height, holder=holder)
    image = image.to(dtype)
    alpha = alpha.to(dtype)
    depth = None
    if render_depth:
        image, depth = image[..., :-1], image[..., -1:]
        if depth_mode == "expected":
            depth = depth / alpha.clamp_min(K_.DEPTH_ALPHA_EPS)
    if background is not None:
        image = image + (1.0 - alpha) * background.to(dtype)
    info = {
        "backend": chosen,
        "means2d": means2d,
        "radii": proj.radii,
        "visible": proj.visible,
        "depths": proj.depths,
        "conics": proj.conics,
        "opacities": proj.opacities,
        "n_intersections": (
            impl.last_stats.get("forward", {}).get("n_intersections", -1)
            if chosen == "cpu"
            else torch_reference.count_intersections(proj)
        ),
        "n_gaussians": n,
        "width": width,
        "height": height,
        "tile_size": K_.TILE_SIZE,
    }
    if depth is not None:
        info["depth"] = depth
    return image, alpha, info


class _FallBack(Exception):
    pass


def _rasterize_cuda(
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
    render_depth,
    depth_mode,
    options,
    *,
    explicit: bool,
):
    global _cuda_failure
    from . import cuda_backend

    try:
        image, alpha, depth, info = cuda_backend.rasterize(
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
            render_depth=render_depth,
            depth_mode=depth_mode,
            **options,
        )
    except cuda_backend.GsplatUnavailable as exc:
        if explicit:
            raise
        _cuda_failure = exc
        _warn_once("cuda", f"gsplat is not usable ({exc}); rendering CUDA tensors with the torch reference")
        raise _FallBack() from exc
    info.update(
        backend="cuda", n_gaussians=means.shape[0], width=width, height=height, tile_size=K_.TILE_SIZE
    )
    if depth is not None:
        info["depth"] = depth
    return image, alpha, info
