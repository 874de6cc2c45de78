"""The `cuda` backend: gsplat's CUDA kernels behind stg_node's backend interface.

We call gsplat's documented high-level ``gsplat.rasterization`` (the path measured on an H100,
docs/BENCHMARKS.md) with one camera (``viewmats[None]``, ``Ks[None]``), ``packed=False``
(per-Gaussian outputs, so the projection is [N, ...] like the other backends'),
``tile_size=16``, our eps2d/near/far/radius_clip, ``render_mode="RGB+D"`` when depth is asked
(the api layer divides for expected depth and blends the background, as for every backend),
``absgrad=True`` when gradients are needed and ``rasterize_mode="antialiased"`` when asked.
Its compiled constants (alpha clamp 0.999, alpha threshold 1/255, transmittance stop 1e-4,
3.33 sigma) are the values in constants.py, read from the gsplat release the ``cuda`` extra
pins (`constants.GSPLAT_VERSION`); an older gsplat is refused, a newer one warned about.

gsplat is a pure-Python wheel that JIT-compiles its kernels with nvcc on first use (minutes).
`ensure_kernels` does that build with a progress message before the first render, and
``stg-splat-prebuild`` (splat/prebuild.py) does it ahead of time; the result is cached in torch's
extension directory (`gsplat_build_dir`). gsplat imports ``packaging`` without declaring it;
every failure becomes a `GsplatUnavailable` naming the fix.

``info["means2d"]`` must behave as in the other backends: an [N, 2] differentiable tensor whose
``.grad`` (total gradient) and ``.absgrad`` are filled by backward. gsplat's own means2d is
[1, N, 2] and gets ``.absgrad`` set by its rasterizer backward; a hook on it copies the full
gradient and absgrad onto our [N, 2] view.

gsplat divides by the number of Gaussians and by the image area when it launches kernels (a
process-killing SIGFPE for 0 Gaussians); the api layer never calls a backend for an empty
scene or a zero-area image. An all-culled scene is safe in 1.5.3 (its intersection, offset
and rasterizer-backward launches return early on zero intersections).
"""

from __future__ import annotations

import importlib
import importlib.util
import logging
import threading
import time
from pathlib import Path

import torch

from ..progress import wait_with_progress
from . import constants as K_
from .types import BackendOutput, BackendUnavailable, Projection, RenderRequest, RenderStats

log = logging.getLogger(__name__)

#: gsplat's JIT extension name (gsplat/cuda/_backend.py).
GSPLAT_EXTENSION = "gsplat_cuda"


class GsplatUnavailable(BackendUnavailable):
    """gsplat is missing, too old, or fails to import or compile, on this machine."""


_INSTALL_HINT = "install the cuda extra: pip install 'stg_node[cuda]'"
_warned_version: set[str] = set()


def _check_version(gsplat) -> None:
    from packaging.version import Version

    have = str(getattr(gsplat, "__version__", "0"))
    if Version(have) < Version(K_.GSPLAT_VERSION):
        raise GsplatUnavailable(
            f"gsplat {have} is older than {K_.GSPLAT_VERSION}, whose rules and constants the other "
            f"backends follow; {_INSTALL_HINT}"
        )
    if Version(have) != Version(K_.GSPLAT_VERSION) and have not in _warned_version:
        _warned_version.add(have)
        log.warning(
            "gsplat %s: stg_node's constants were read from gsplat %s; renders may differ from the "
            "cpu and torch backends if its kernels changed",
            have,
            K_.GSPLAT_VERSION,
        )


def import_gsplat():
    try:
        import packaging  # noqa: F401  (gsplat imports it without declaring it)
    except ImportError as exc:
        raise GsplatUnavailable(
            f"gsplat needs the `packaging` package, which it does not declare; {_INSTALL_HINT}"
        ) from exc
    try:
        import gsplat
    except Exception as exc:  # ImportError, or a failing build at import
        raise GsplatUnavailable(
            f"gsplat is not usable ({type(exc).__name__}: {exc}); {_INSTALL_HINT}"
        ) from exc
    _check_version(gsplat)
    return gsplat


def gsplat_build_dir() -> Path:
    """Where gsplat's JIT build lives: torch's extension cache ($TORCH_EXTENSIONS_DIR, else
    ~/.cache/torch_extensions/py<ver>_cu<ver>/gsplat_cuda)."""
    from torch.utils.cpp_extension import _get_build_directory

    return Path(_get_build_directory(GSPLAT_EXTENSION, verbose=False))


def kernels_built() -> bool:
    """True if gsplat's kernels load without compiling: a prebuilt wheel, or a cached JIT build."""
    if importlib.util.find_spec("gsplat.csrc") is not None:
        return True
    return (gsplat_build_dir() / f"{GSPLAT_EXTENSION}.so").is_file()


def _load_gsplat_kernels():
    """gsplat's kernel module; importing it compiles the kernels when they are not cached."""
    return importlib.import_module("gsplat.cuda._backend")


_kernels_lock = threading.Lock()
_kernels_ready = False


def ensure_kernels(show_progress: bool = True) -> None:
    """Load gsplat's CUDA kernels, building them first (minutes, once) with a progress
    message if they are not cached; GsplatUnavailable if they cannot be built or loaded."""
    global _kernels_ready
    with _kernels_lock:
        if _kernels_ready:
            return
        import_gsplat()
        build = not kernels_built()
        if build:
            log.warning(
                "building gsplat's CUDA kernels: first use on this machine, this takes several "
                "minutes and is cached in %s (to build ahead: stg-splat-prebuild)",
                gsplat_build_dir(),
            )
        t0 = time.monotonic()
        try:
            module = wait_with_progress(
                _load_gsplat_kernels,
                desc="building gsplat CUDA kernels",
                enabled=build and show_progress,
            )
        except Exception as exc:
            raise GsplatUnavailable(
                f"gsplat's CUDA kernels failed to build or load ({type(exc).__name__}: {exc}); "
                f"the build directory is {gsplat_build_dir()}"
            ) from exc
        if getattr(module, "_C", None) is None:
            raise GsplatUnavailable(
                "gsplat found no CUDA toolkit (nvcc) to build or load its kernels; install the CUDA "
                f"toolkit matching torch (CUDA {torch.version.cuda}) or set CUDA_HOME"
            )
        if build:
            log.warning("gsplat's CUDA kernels are built (%.0f s)", time.monotonic() - t0)
        _kernels_ready = True


def _attach_means2d_grads(base: torch.Tensor, visible: torch.Tensor) -> torch.Tensor:
    """An [N, 2] tensor of gsplat's [1, N, 2] means2d (0 where culled) whose ``.grad`` is the
    total dL/dmeans2d and ``.absgrad`` gsplat's AbsGS statistic, both accumulating.

    ``view.grad`` gets, through retain_grad, the gradient of everything computed from `view`
    itself; a hook on `base` then adds the part that reached `base` by other paths (gsplat's
    rasterizer), i.e. the base gradient minus what `view` passed down to it.
    """
    mask = visible[:, None]
    view = torch.where(mask, base[0], torch.zeros_like(base[0]))
    if not base.requires_grad:
        return view
    view.retain_grad()
    passed_down: dict[str, torch.Tensor | None] = {"grad": None}

    def on_view(grad):
        passed_down["grad"] = torch.where(mask, grad, torch.zeros_like(grad))

    def on_base(grad):
        rest = grad[0].detach()
        if passed_down["grad"] is not None:
            rest = rest - passed_down["grad"].detach()
            passed_down["grad"] = None
        view.grad = rest.clone() if view.grad is None else view.grad + rest
        absgrad = getattr(base, "absgrad", None)
        if absgrad is not None:
            prev = getattr(view, "absgrad", None)
            view.absgrad = absgrad[0].detach().clone() if prev is None else prev + absgrad[0].detach()

    view.register_hook(on_view)
    base.register_hook(on_base)
    return view


class CudaBackend:
    """gsplat's fused render (float32) on CUDA tensors; see the module docstring."""

    name = "cuda"
    device_type = "cuda"
    description = "gsplat"

    def check(self) -> None:
        """gsplat imports and is recent enough (its kernels are built on the first render)."""
        if not torch.cuda.is_available():
            raise GsplatUnavailable("no CUDA device")
        import_gsplat()

    def render(self, request: RenderRequest) -> BackendOutput:
        gsplat = import_gsplat()
        ensure_kernels()
        o = request.options
        dtype = request.means.dtype  # gsplat's kernels are float32; autograd casts gradients back
        means, quats, scales, opacities, colors = (
            t.float()
            for t in (request.means, request.quats, request.scales, request.opacities, request.colors)
        )
        needs_grad = any(t.requires_grad for t in (means, quats, scales, opacities))
        renders, alphas, meta = gsplat.rasterization(
            means,
            quats,
            scales,
            opacities,
            colors,
            viewmats=request.viewmat[None].float(),
            Ks=request.K[None].float(),
            width=request.width,
            height=request.height,
            near_plane=o.near_plane,
            far_plane=o.far_plane,
            radius_clip=o.radius_clip,
            eps2d=o.eps2d,
            packed=False,
            tile_size=K_.TILE_SIZE,
            render_mode="RGB+D" if o.render_depth else "RGB",
            absgrad=needs_grad,
            rasterize_mode="antialiased" if o.antialiased else "classic",
        )
        image, alpha = renders[0].to(dtype), alphas[0].to(dtype)
        depth = None
        if o.render_depth:
            image, depth = image[..., :-1], image[..., -1:]
        radii = meta["radii"][0].to(torch.int32)  # [N, 2]
        visible = (radii > 0).all(dim=-1)
        # gsplat leaves culled rows unwritten: zero them, as the other backends do.
        vis = visible[:, None]
        projection = Projection(
            means2d=_attach_means2d_grads(meta["means2d"], visible),
            conics=torch.where(vis, meta["conics"][0], torch.zeros_like(meta["conics"][0])),
            depths=torch.where(visible, meta["depths"][0], torch.zeros_like(meta["depths"][0])),
            opacities=torch.where(visible, meta["opacities"][0], torch.zeros_like(meta["opacities"][0])),
            radii=torch.where(vis, radii, torch.zeros_like(radii)),
            bbox=None,
            visible=visible,
        )
        isect_ids = meta.get("isect_ids")
        stats = RenderStats(n_intersections=int(isect_ids.numel()) if isect_ids is not None else -1)
        return BackendOutput(image, alpha, depth, projection, stats)


BACKEND = CudaBackend()
