"""The `cpu` backend: autograd wrappers around the C++/OpenMP kernels (csrc/, built by build.py).

Two autograd Functions are the two stages of `CpuBackend` (a `TwoStageBackend`): ``_Project``
(3D -> screen-space Gaussians) and ``_Rasterize`` (screen space -> image). Their backward
passes are the hand-written C++ ones. The thread count is torch's (``torch.get_num_threads()``,
set by ``stg_node.threads``).

Tensors are computed in float32 (inputs of another float dtype are cast, and gradients are
cast back by autograd). ``viewmat`` and ``K`` are not differentiated. Per-stage timings and
counters go into the render's `RenderStats.stages` (``info["stats"]``): "project" and
"forward" when rendering, "project_backward" and "backward" once backward has run.
"""

from __future__ import annotations

import time

import torch

from . import constants as K_
from .backend import TwoStageBackend, plane_in_dtype
from .build import load_kernels
from .types import AbsGradHolder, Projection, RenderRequest, RenderStats


def settings_vector(
    *,
    near_plane: float,
    far_plane: float,
    eps2d: float,
    radius_clip: float,
    antialiased: bool,
    max_intersections: int,
) -> list[float]:
    """The kernels' `settings` argument, in the order of SettingIndex in splat_kernels.h."""
    return [
        float(near_plane),
        float(far_plane),
        float(eps2d),
        float(radius_clip),
        K_.ALPHA_MIN,
        K_.ALPHA_MAX,
        K_.TRANSMITTANCE_MIN,
        K_.SIGMA_EXTENT_MAX,
        K_.QUAT_NORM_EPS,
        K_.COMPENSATION_GRAD_EPS,
        K_.FRUSTUM_MARGIN,
        1.0 if antialiased else 0.0,
        float(max_intersections),
        float(K_.RADIUS_REPORT_MAX),
    ]


def _stats_dict(stats: torch.Tensor) -> dict[str, float]:
    s = stats.tolist()
    return {
        "ms_sort": s[0],
        "ms_bin": s[1],
        "ms_raster": s[2],
        "ms_reduce": s[3],
        "n_drawn": int(s[4]),  # visible Gaussians covering a pixel centre
        "n_intersections": int(s[5]),
        "n_chunks": int(s[6]),
    }


def _f32(t: torch.Tensor) -> torch.Tensor:
    return t.detach().to(torch.float32).contiguous()


class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmat, K, width, height, settings, stages):
        ops = load_kernels().ops
        threads = torch.get_num_threads()
        vm = viewmat.detach().to(torch.float64).contiguous()
        kk = K.detach().to(torch.float64).contiguous()
        m, q, s, o = _f32(means), _f32(quats), _f32(scales), _f32(opacities)
        t0 = time.perf_counter()
        means2d, conics, depths, opac_eff, _comp, radii, bbox, visible = ops.project_fwd(
            m, q, s, o, vm, kk, width, height, settings, threads
        )
        stages["project"] = {"ms": (time.perf_counter() - t0) * 1e3}
        ctx.save_for_backward(m, q, s, o, vm, kk, visible)
        ctx.args = (width, height, settings, stages)
        ctx.mark_non_differentiable(radii, bbox, visible)
        return means2d, conics, depths, opac_eff, radii, bbox, visible

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_depths, g_opac, _g_radii, _g_bbox, _g_visible):
        m, q, s, o, vm, kk, visible = ctx.saved_tensors
        width, height, settings, stages = ctx.args
        ops = load_kernels().ops

        def grad_or_zeros(g, like):
            return torch.zeros_like(like) if g is None else _f32(g)

        t0 = time.perf_counter()
        g_means, g_quats, g_scales, g_opac = ops.project_bwd(
            m,
            q,
            s,
            o,
            vm,
            kk,
            width,
            height,
            settings,
            torch.get_num_threads(),
            visible,
            grad_or_zeros(g_means2d, m[:, :2]),
            grad_or_zeros(g_conics, m),
            grad_or_zeros(g_depths, o),
            grad_or_zeros(g_opac, o),
        )
        stages["project_backward"] = {"ms": (time.perf_counter() - t0) * 1e3}
        return g_means, g_quats, g_scales, g_opac, None, None, None, None, None, None


class _Rasterize(torch.autograd.Function):
    @staticmethod
    def forward(
        ctx,
        means2d,
        conics,
        opacities,
        colors,
        depths,
        bbox,
        visible,
        width,
        height,
        settings,
        holder,
        stages,
    ):
        ops = load_kernels().ops
        args = (
            _f32(means2d),
            _f32(conics),
            _f32(opacities),
            _f32(colors),
            _f32(depths),
            bbox.contiguous(),
            visible.contiguous(),
        )
        color, T, last, stats = ops.raster_fwd(*args, width, height, settings, torch.get_num_threads())
        stages["forward"] = _stats_dict(stats)
        ctx.save_for_backward(*args, T, last)
        ctx.args = (width, height, settings, holder, stages)
        alpha = (1.0 - T).unsqueeze(-1)
        return color, alpha

    @staticmethod
    def backward(ctx, g_color, g_alpha):
        means2d, conics, opacities, colors, depths, bbox, visible, T, last = ctx.saved_tensors
        width, height, settings, holder, stages = ctx.args
        ops = load_kernels().ops
        g_color = torch.zeros((height, width, colors.shape[1])) if g_color is None else _f32(g_color)
        g_alpha = torch.zeros((height, width)) if g_alpha is None else _f32(g_alpha[..., 0])
        g_means2d, g_conics, g_opac, g_colors, g_abs, stats = ops.raster_bwd(
            means2d,
            conics,
            opacities,
            colors,
            depths,
            bbox,
            visible,
            width,
            height,
            settings,
            torch.get_num_threads(),
            T,
            last,
            g_color,
            g_alpha,
        )
        stages["backward"] = _stats_dict(stats)
        if holder is not None:
            holder.add_absgrad(None, g_abs)
        return g_means2d, g_conics, g_opac, g_colors, None, None, None, None, None, None, None, None


class CpuBackend(TwoStageBackend):
    """The C++/OpenMP kernels, float32, on CPU tensors."""

    name = "cpu"
    device_type = "cpu"
    description = "C++/OpenMP kernels"

    def check(self) -> None:
        load_kernels()  # builds them on the first call (cached on disk); ExtensionUnavailable if not

    def working_dtype(self, dtype: torch.dtype) -> torch.dtype:
        return torch.float32

    def _settings(self, request: RenderRequest) -> list[float]:
        o = request.options
        return settings_vector(
            near_plane=plane_in_dtype(o.near_plane, torch.float32),
            far_plane=plane_in_dtype(o.far_plane, torch.float32),
            eps2d=o.eps2d,
            radius_clip=o.radius_clip,
            antialiased=o.antialiased,
            max_intersections=o.max_intersections,
        )

    def project(self, request: RenderRequest, tensors, stats: RenderStats) -> Projection:
        means2d, conics, depths, opac_eff, radii, bbox, visible = _Project.apply(
            *tensors,
            request.viewmat,
            request.K,
            int(request.width),
            int(request.height),
            self._settings(request),
            stats.stages,
        )
        return Projection(
            means2d=means2d,
            conics=conics,
            depths=depths,
            opacities=opac_eff,
            radii=radii,
            bbox=bbox,
            visible=visible,
        )

    def rasterize(
        self,
        request: RenderRequest,
        projection: Projection,
        colors: torch.Tensor,
        holder: AbsGradHolder | None,
        stats: RenderStats,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        image, alpha = _Rasterize.apply(
            projection.means2d,
            projection.conics,
            projection.opacities,
            colors,
            projection.depths.detach(),
            projection.bbox,
            projection.visible,
            int(request.width),
            int(request.height),
            self._settings(request),
            holder,
            stats.stages,
        )
        stats.n_intersections = int(stats.stages["forward"]["n_intersections"])
        return image, alpha


BACKEND = CpuBackend()
