"""Which Gaussians a camera cannot see, known before they are shaded: a conservative frustum test.

A model that computes its Gaussians' colours (a network per Gaussian) or poses them (skinning)
before splatting can drop the ones the rasterizer is going to cull anyway and skip that work.
``may_be_visible`` keeps every Gaussian the rasterizer could draw: it applies the rasterizer's
own depth rule (docs/SPLAT.md, "Which Gaussians are visible", rule 1) and a bound of its image
rule (rule 5): the screen radius of a Gaussian is at most ``SIGMA_EXTENT_MAX`` standard
deviations of its projected covariance, whose variance along x is at most ``|J_x|^2 s_max^2 +
eps2d`` (``J_x`` the row of the EWA Jacobian, ``s_max`` the largest scale), plus a pixel for the
rounding up and float32. What it drops draws nothing; what it keeps may still be culled there.
"""

from __future__ import annotations

import torch

from . import constants as K_
from .build import load_kernels
from .types import BackendUnavailable

MARGIN_PX = 1.0  # the radius is rounded up to whole pixels; float32 against the kernels' float64


def may_be_visible(
    means: torch.Tensor,
    scales: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    *,
    near_plane: float = K_.NEAR_PLANE,
    far_plane: float = K_.FAR_PLANE,
    eps2d: float = K_.LOW_PASS_EPS2D,
) -> torch.Tensor:
    """``(N,)`` bool: False only for Gaussians (world ``means (N, 3)``, activated ``scales (N, 3)``)
    that ``rasterize`` with this camera culls (behind or beyond the depth planes, or whose screen
    box misses the image). No gradient. The C++ kernel on float32 CPU tensors, else
    :func:`may_be_visible_torch` (the reference)."""
    if means.device.type == "cpu" and means.dtype == torch.float32 and scales.dtype == torch.float32:
        try:
            ops = load_kernels().ops
        except BackendUnavailable:
            ops = None
        if ops is not None:
            from .cpu_backend import settings_vector

            settings = settings_vector(
                near_plane=near_plane,
                far_plane=far_plane,
                eps2d=eps2d,
                radius_clip=0.0,
                antialiased=False,
                max_intersections=K_.MAX_INTERSECTIONS_PER_CHUNK,
            )
            return ops.may_be_visible(
                means.detach().contiguous(),
                scales.detach().contiguous(),
                viewmat.detach().to(torch.float64).contiguous(),
                K.detach().to(torch.float64).contiguous(),
                int(width),
                int(height),
                settings,
                MARGIN_PX,
                torch.get_num_threads(),
            )
    return may_be_visible_torch(
        means, scales, viewmat, K, width, height, near_plane=near_plane, far_plane=far_plane, eps2d=eps2d
    )


def may_be_visible_torch(
    means: torch.Tensor,
    scales: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    *,
    near_plane: float = K_.NEAR_PLANE,
    far_plane: float = K_.FAR_PLANE,
    eps2d: float = K_.LOW_PASS_EPS2D,
) -> torch.Tensor:
    """:func:`may_be_visible` in torch (any device and dtype): the reference of the kernel."""
    with torch.no_grad():
        R = viewmat[:3, :3].to(means.dtype)
        t = viewmat[:3, 3].to(means.dtype)
        p = means @ R.T + t
        z = p[:, 2]
        # written as "culled where", so a NaN is kept and reaches the rasterizer's input checks
        out_of_depth = (z < near_plane) | (z > far_plane)
        zs = z.clamp_min(near_plane)
        fx, fy, cx, cy = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
        ux, uy = p[:, 0] / zs, p[:, 1] / zs
        # the EWA Jacobian's x/z, y/z are clamped to the frustum widened by FRUSTUM_MARGIN
        tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
        lim_xp = (width - cx) / fx + K_.FRUSTUM_MARGIN * tan_x
        lim_xn = cx / fx + K_.FRUSTUM_MARGIN * tan_x
        lim_yp = (height - cy) / fy + K_.FRUSTUM_MARGIN * tan_y
        lim_yn = cy / fy + K_.FRUSTUM_MARGIN * tan_y
        tx = ux.clamp(-lim_xn, lim_xp)
        ty = uy.clamp(-lim_yn, lim_yp)
        s_max = scales.amax(dim=1)
        jx2 = (fx / zs) ** 2 * (1.0 + tx * tx)
        jy2 = (fy / zs) ** 2 * (1.0 + ty * ty)
        rx = K_.SIGMA_EXTENT_MAX * (jx2 * s_max * s_max + eps2d).sqrt() + MARGIN_PX
        ry = K_.SIGMA_EXTENT_MAX * (jy2 * s_max * s_max + eps2d).sqrt() + MARGIN_PX
        mx, my = fx * ux + cx, fy * uy + cy
        off_image = (mx + rx <= 0) | (mx - rx >= width) | (my + ry <= 0) | (my - ry >= height)
        return ~(out_of_depth | off_image)
