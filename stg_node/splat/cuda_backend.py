"""The `cuda` backend: gsplat's CUDA kernels behind stg_node's rasterize() contract.

gsplat (the ``cuda`` extra) JIT-compiles its kernels on first use and imports ``packaging``
without declaring it; both failures are turned into a clear `GsplatUnavailable`. We call its
documented high-level ``gsplat.rasterization`` with one camera (``viewmats[None]``,
``Ks[None]``), ``packed=False`` (per-Gaussian outputs, so info tensors are [N, ...] like the
other backends), ``tile_size=16``, our eps2d/near/far/radius_clip, ``absgrad=True`` and
``rasterize_mode="antialiased"`` when asked. gsplat compiles its own alpha/transmittance
thresholds (1/255, 0.99, 1e-4 in the versions we target), equal to constants.py.

``info["means2d"]`` must behave as in the other backends: an [N, 2] differentiable tensor whose
``.grad`` (total gradient) and ``.absgrad`` are filled by backward. gsplat's own means2d is
[1, N, 2] and gets ``.absgrad`` set by its rasterizer backward; a hook on it copies the full
gradient and absgrad onto our [N, 2] view. This path has not been run on a GPU here.
"""

from __future__ import annotations

import torch

from . import constants as K_


class GsplatUnavailable(RuntimeError):
    """gsplat is missing, or fails to import or compile, on this machine."""


def import_gsplat():
    try:
        import packaging  # noqa: F401  (gsplat imports it without declaring it)
    except ImportError as exc:
        raise GsplatUnavailable(
            "gsplat needs the `packaging` package, which it does not declare; "
            "install the cuda extra: pip install 'stg_node[cuda]'"
        ) from exc
    try:
        import gsplat
    except Exception as exc:  # ImportError, or a failing JIT build at import
        raise GsplatUnavailable(
            f"gsplat is not usable ({type(exc).__name__}: {exc}); install the cuda extra: "
            "pip install 'stg_node[cuda]'"
        ) from exc
    return gsplat


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


def rasterize(
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
    *,
    near_plane,
    far_plane,
    eps2d,
    radius_clip,
    antialiased,
    render_depth,
    depth_mode,
):
    """Render with gsplat; returns (image [H, W, C], alpha [H, W, 1], depth or None, info)."""
    gsplat = import_gsplat()
    dtype = means.dtype  # gsplat's kernels are float32; autograd casts the gradients back
    means, quats, scales, opacities, colors = (t.float() for t in (means, quats, scales, opacities, colors))
    needs_grad = any(t.requires_grad for t in (means, quats, scales, opacities))
    if render_depth:
        render_mode = "RGB+ED" if depth_mode == "expected" else "RGB+D"
    else:
        render_mode = "RGB"
    backgrounds = None
    if background is not None:
        backgrounds = background.expand(colors.shape[1])[None].float()
    renders, alphas, meta = gsplat.rasterization(
        means,
        quats,
        scales,
        opacities,
        colors,
        viewmats=viewmat[None].float(),
        Ks=K[None].float(),
        width=width,
        height=height,
        near_plane=near_plane,
        far_plane=far_plane,
        radius_clip=radius_clip,
        eps2d=eps2d,
        packed=False,
        tile_size=K_.TILE_SIZE,
        backgrounds=backgrounds,
        render_mode=render_mode,
        absgrad=needs_grad,
        rasterize_mode="antialiased" if antialiased else "classic",
    )
    renders, alpha = renders[0].to(dtype), alphas[0].to(dtype)
    depth = None
    if render_depth:
        image, depth = renders[..., :-1], renders[..., -1:]
    else:
        image = renders
    radii = meta["radii"][0]
    if radii.dim() == 1:  # gsplat < 1.5: one radius per Gaussian
        radii = torch.stack([radii, radii], dim=-1)
    radii = radii.to(torch.int32)
    visible = (radii > 0).all(dim=-1)
    # gsplat may leave culled rows unwritten: zero them, as the other backends do.
    vis = visible[:, None]
    info = {
        "means2d": _attach_means2d_grads(meta["means2d"], visible),
        "radii": radii,
        "visible": visible,
        "depths": torch.where(visible, meta["depths"][0], torch.zeros_like(meta["depths"][0])),
        "conics": torch.where(vis, meta["conics"][0], torch.zeros_like(meta["conics"][0])),
        "opacities": torch.where(visible, meta["opacities"][0], torch.zeros_like(meta["opacities"][0])),
        "n_intersections": int(meta["isect_ids"].numel()) if meta.get("isect_ids") is not None else -1,
    }
    return image, alpha, depth, info
