"""Which Gaussians are visible: gsplat 1.5.3's culling rules, on the cpu and torch backends.

The oracle is a line-by-line transcription of gsplat 1.5.3's projection kernel
(gsplat/cuda/csrc/ProjectionEWA3DGSFused.cu, ``projection_ewa_3dgs_fused_fwd_kernel`` with
``persp_proj`` and ``add_blur`` from cuda/include/Utils.cuh), written here in float64 from
that source and not from our backends: depth planes, det of the dilated covariance, opacity
(x compensation) below 1/255, the opacity-aware extent min(3.33, sqrt(2 ln(o / (1/255)))),
radius = ceil(extent * sqrt(cov2d diagonal)), radius_clip, and the image test on
mean +- radius. docs/SPLAT.md ("Which Gaussians are visible") states the rule.
"""

from __future__ import annotations

import math

import pytest
import torch

from stg_node.splat import rasterize
from stg_node.splat.api import available_backends, sanitize_quats
from stg_node.splat.scenes import random_scene

CPU_BACKENDS = [b for b in available_backends() if b != "cuda"]


def _gsplat_1_5_3_radii(means, quats, scales, opacities, viewmat, K, width, height, eps2d=0.3, near=0.01,
                        far=1e10, radius_clip=0.0, antialiased=False):  # fmt: skip
    """[N, 2] radii as gsplat 1.5.3's fused projection writes them (0 = culled), in float64."""
    out = []
    R, t = viewmat[:3, :3].double(), viewmat[:3, 3].double()
    fx, fy, cx, cy = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    for mean, quat, scale, opacity in zip(means.double(), quats.double(), scales.double(), opacities.double(),
                                          strict=True):  # fmt: skip
        mean_c = R @ mean + t
        if mean_c[2] < near or mean_c[2] > far:
            out.append((0, 0))
            continue
        w, x, y, z = (quat / quat.norm()).tolist()  # quat_to_rotmat: q * rsqrt(|q|^2)
        rot = torch.tensor(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ],
            dtype=torch.float64,
        )
        m = rot @ torch.diag(scale)
        covar_c = R @ (m @ m.T) @ R.T
        # persp_proj
        px, py, pz = mean_c.tolist()
        tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
        lim_x_pos, lim_x_neg = (width - cx) / fx + 0.3 * tan_fovx, cx / fx + 0.3 * tan_fovx
        lim_y_pos, lim_y_neg = (height - cy) / fy + 0.3 * tan_fovy, cy / fy + 0.3 * tan_fovy
        rz = 1.0 / pz
        tx = pz * min(lim_x_pos, max(-lim_x_neg, px * rz))
        ty = pz * min(lim_y_pos, max(-lim_y_neg, py * rz))
        J = torch.tensor(
            [[fx * rz, 0.0, -fx * tx * rz * rz], [0.0, fy * rz, -fy * ty * rz * rz]], dtype=torch.float64
        )
        cov2d = J @ covar_c @ J.T
        mean2d = (fx * px * rz + cx, fy * py * rz + cy)
        # add_blur
        det_orig = float(cov2d[0, 0] * cov2d[1, 1] - cov2d[0, 1] * cov2d[1, 0])
        cov2d[0, 0] += eps2d
        cov2d[1, 1] += eps2d
        det = float(cov2d[0, 0] * cov2d[1, 1] - cov2d[0, 1] * cov2d[1, 0])
        compensation = math.sqrt(max(0.0, det_orig / det))
        if det <= 0.0:
            out.append((0, 0))
            continue
        extend = 3.33
        o = float(opacity) * (compensation if antialiased else 1.0)
        if o < 1.0 / 255.0:
            out.append((0, 0))
            continue
        extend = min(extend, math.sqrt(2.0 * math.log(o / (1.0 / 255.0))))
        radius_x = math.ceil(extend * math.sqrt(float(cov2d[0, 0])))
        radius_y = math.ceil(extend * math.sqrt(float(cov2d[1, 1])))
        if radius_x <= radius_clip and radius_y <= radius_clip:
            out.append((0, 0))
            continue
        if (
            mean2d[0] + radius_x <= 0
            or mean2d[0] - radius_x >= width
            or mean2d[1] + radius_y <= 0
            or mean2d[1] - radius_y >= height
        ):
            out.append((0, 0))
            continue
        out.append((radius_x, radius_y))
    return torch.tensor(out, dtype=torch.int32).reshape(-1, 2)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
@pytest.mark.parametrize(
    "options", [{}, {"antialiased": True}, {"radius_clip": 3.0}], ids=["classic", "aa", "clip"]
)
def test_visible_set_and_radii_are_gsplats(backend, options):
    """2000 Gaussians, many of them across the image border: the same visible set and radii as
    gsplat's kernel (the earlier pixel-centre rule disagreed on ~1 % of them)."""
    scene, viewmat, K = random_scene(2000, 128, 96, seed=4, max_opacity=1.0)
    _, _, info = rasterize(*scene.params(), viewmat, K, 128, 96, backend=backend, **options)
    expected = _gsplat_1_5_3_radii(
        scene.means,
        scene.quats,
        scene.scales,
        scene.opacities,
        viewmat,
        K,
        128,
        96,
        radius_clip=options.get("radius_clip", 0.0),
        antialiased=options.get("antialiased", False),
    )
    visible = (expected > 0).all(dim=1)
    assert 800 < int(visible.sum()) < 1950  # both culled and kept Gaussians are exercised
    assert torch.equal(info["visible"], visible)
    assert torch.equal(info["radii"], expected)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_a_gaussian_less_than_half_a_pixel_inside_is_visible_but_draws_nothing(backend):
    """gsplat's image test is on mean +- radius, not on pixel centres: a tiny Gaussian (the 0.3
    px^2 dilation alone: radius ceil(3.26 * 0.548) = 2 px at opacity 0.8) whose box reaches
    0.25 px into the image is visible (radii > 0) but covers no pixel centre; at 0 px it is
    culled; at 1 px it covers the first column (where its alpha is 0.012 > 1/255)."""
    f, depth, width, height = 32.0, 2.0, 32, 24  # u = 16 x + 16: the centres below are exact
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    us = [-1.75, -2.0, -1.0, width + 1.75]  # mean u; radius 2: reach 0.25 / 0 / 1 px in; 31.75
    means = torch.tensor([[(u - width / 2) / f * depth, 0.0, depth] for u in us])
    n = len(us)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * n)
    scales = torch.full((n, 3), 1e-6)
    opacities = torch.full((n,), 0.8)
    expected = _gsplat_1_5_3_radii(means, quats, scales, opacities, torch.eye(4), K, width, height)
    assert expected.tolist() == [[2, 2], [0, 0], [2, 2], [2, 2]]
    for i in range(n):
        params = [t[i : i + 1] for t in (means, quats, scales, opacities, torch.ones(n, 3))]
        _, alpha, info = rasterize(*params, torch.eye(4), K, width, height, backend=backend)
        assert info["radii"].tolist() == [expected[i].tolist()]
        drawn = alpha.max().item() > 0
        assert drawn == (i == 2), (i, alpha.max().item())
        assert info["n_intersections"] == (1 if i == 2 else 0)


def test_zero_quaternions_become_the_identity_before_any_backend():
    """Every component below 1e-12 in magnitude -> (1, 0, 0, 0), zero gradient; the rest untouched."""
    eps = 1e-12
    rows = [
        [0.0] * 4,
        [-0.9 * eps, 0.0, 0.0, 0.0],
        [0.6 * eps] * 4,
        [1.1 * eps, 0.0, 0.0, 0.0],
        [0.0, 2.0, 0.0, 0.0],
    ]
    q = torch.tensor(rows, dtype=torch.float64, requires_grad=True)
    out = sanitize_quats(q)
    assert out.tolist() == [[1.0, 0, 0, 0]] * 3 + rows[3:]
    out.sum().backward()
    assert q.grad.tolist() == [[0.0] * 4] * 3 + [[1.0] * 4] * 2
    assert sanitize_quats(q.float())[2].tolist() == [1.0, 0, 0, 0]
    unit = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.5, 0.5, 0.5, 0.5]])
    assert sanitize_quats(unit) is unit  # the common case costs one reduction, no copy
    assert sanitize_quats(torch.zeros(0, 4)).shape == (0, 4)
