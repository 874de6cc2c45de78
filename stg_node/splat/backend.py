"""The one interface every splat backend implements, and the driver the two-stage ones share.

A backend is one file (cpu_backend.py, cuda_backend.py, torch_reference.py) holding an object
`BACKEND` that answers `SplatBackend`: its `name`, the `device_type` of the tensors it renders
(None: any), `check()` (raises BackendUnavailable with the reason unless usable here) and
`render(RenderRequest) -> BackendOutput`. api.py registers it by name; everything shared
(checks, empty scenes, quaternions, background, expected depth, info) stays in the api layer.

Backends that split the work into a projection and a rasterization, as the cpu kernels and
the torch reference do, subclass `TwoStageBackend` and write only those two stages; the
driver here adds the depth channel, wires ``means2d.grad``/``.absgrad`` and skips the
rasterizer when every Gaussian is culled. A fused backend (gsplat) implements `render`
itself and must give the same guarantees.
"""

from __future__ import annotations

from typing import Protocol

import torch

from .types import AbsGradHolder, BackendOutput, Projection, RenderRequest, RenderStats


class SplatBackend(Protocol):
    name: str  # "cpu", "cuda", "torch": the value of rasterize(backend=...) and info["backend"]
    device_type: str | None  # tensors it renders ("cpu", "cuda"); None: any device
    description: str  # for logs: "C++/OpenMP kernels", "gsplat", ...

    def check(self) -> None:
        """Raise BackendUnavailable, naming the reason, unless this backend can run here (it may
        build its kernels to find out)."""
        ...

    def render(self, request: RenderRequest) -> BackendOutput:
        """Render one camera; raises BackendUnavailable if it turns out not to run here."""
        ...


def plane_in_dtype(value: float, dtype: torch.dtype) -> float:
    """A near/far plane rounded to the working precision, so that a centre placed exactly on
    the near plane in float32 is kept (as gsplat, which compares in float32, keeps it)."""
    return float(torch.tensor(value, dtype=dtype))


def zero_grad_anchor(tensors) -> torch.Tensor | float:
    """0 * (sum of every tensor that needs a gradient): added to outputs that do not otherwise
    depend on the inputs, so backward still reaches them (with zero gradients)."""
    parts = [t.sum() for t in tensors if t.requires_grad]
    return sum(parts) * 0.0 if parts else 0.0


def track_means2d(means2d: torch.Tensor) -> AbsGradHolder | None:
    """Make ``means2d.grad`` (retain_grad) and ``.absgrad`` (the holder) appear after backward."""
    if not means2d.requires_grad:
        return None
    means2d.retain_grad()
    return AbsGradHolder(means2d)


def blank_images(
    request: RenderRequest, projection: Projection, holder: AbsGradHolder | None, dtype: torch.dtype
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """What a render with nothing to draw is: image, alpha (and depth) all zero, still in the
    autograd graph of every input and of the projection, and ``means2d.absgrad`` (zeros) set
    by backward as a rasterizer would set it."""
    h, w = request.height, request.width
    device = request.means.device
    anchor = zero_grad_anchor(
        (
            request.means,
            request.quats,
            request.scales,
            request.opacities,
            request.colors,
            projection.means2d,
            projection.conics,
            projection.opacities,
            projection.depths,
        )
    )
    if holder is not None:
        m2 = projection.means2d
        m2.register_hook(lambda grad: holder.add_absgrad(None, torch.zeros_like(grad)))
    image = torch.zeros((h, w, request.colors.shape[1]), dtype=dtype, device=device) + anchor
    alpha = torch.zeros((h, w, 1), dtype=dtype, device=device) + anchor
    depth = (
        torch.zeros((h, w, 1), dtype=dtype, device=device) + anchor if request.options.render_depth else None
    )
    return image, alpha, depth


class TwoStageBackend:
    """A backend written as `project` then `rasterize`; `render` composes them."""

    name: str
    device_type: str | None
    description: str

    def check(self) -> None:
        return None

    def working_dtype(self, dtype: torch.dtype) -> torch.dtype:
        """The dtype the stages compute in (outputs are cast back to the inputs' dtype)."""
        return dtype

    def project(self, request: RenderRequest, tensors, stats: RenderStats) -> Projection:
        """tensors: (means, quats, scales, opacities) in the working dtype."""
        raise NotImplementedError

    def rasterize(
        self,
        request: RenderRequest,
        projection: Projection,
        colors: torch.Tensor,
        holder: AbsGradHolder | None,
        stats: RenderStats,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(image [H, W, C'], alpha [H, W, 1]) of the projected Gaussians, no background;
        sets stats.n_intersections."""
        raise NotImplementedError

    def render(self, request: RenderRequest) -> BackendOutput:
        dtype = request.means.dtype
        work = self.working_dtype(dtype)
        means, quats, scales, opacities, colors = (
            t.to(work)
            for t in (request.means, request.quats, request.scales, request.opacities, request.colors)
        )
        stats = RenderStats()
        proj = self.project(request, (means, quats, scales, opacities), stats)
        holder = track_means2d(proj.means2d)
        if not bool(proj.visible.any()):  # (visible ones that draw nothing are cheap either way)
            image, alpha, depth = blank_images(request, proj, holder, dtype)
            stats.n_intersections = 0
            return BackendOutput(image, alpha, depth, proj, stats)
        if request.options.render_depth:
            colors = torch.cat([colors, proj.depths[:, None].to(colors.dtype)], dim=1)
        image, alpha = self.rasterize(request, proj, colors, holder, stats)
        image, alpha = image.to(dtype), alpha.to(dtype)
        depth = None
        if request.options.render_depth:
            image, depth = image[..., :-1], image[..., -1:]
        return BackendOutput(image, alpha, depth, proj, stats)
