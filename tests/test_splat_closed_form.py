"""Renders checked against closed forms: one Gaussian facing the camera is an analytic 2D
Gaussian (with the 0.3 low-pass dilation), and the torch reference's gradients are checked
numerically (float64 gradcheck)."""

from __future__ import annotations

import math

import pytest
import torch

from stg_node.splat import constants, rasterize
from stg_node.splat.api import available_backends

BACKENDS = [b for b in available_backends() if b != "cuda"]


def _one_gaussian(scale: float, depth: float, opacity: float, dtype=torch.float64):
    means = torch.tensor([[0.0, 0.0, depth]], dtype=dtype)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=dtype)
    scales = torch.full((1, 3), scale, dtype=dtype)
    opacities = torch.tensor([opacity], dtype=dtype)
    colors = torch.tensor([[0.2, 0.5, 1.0]], dtype=dtype)
    return means, quats, scales, opacities, colors


def _analytic_alpha(width, height, f, cx, cy, scale, depth, opacity, antialiased=False):
    """alpha(u, v) of one isotropic Gaussian at the optical axis, from the EWA formula."""
    var = (f * scale / depth) ** 2
    var_dilated = var + constants.LOW_PASS_EPS2D
    o = opacity * (var / var_dilated if antialiased else 1.0)  # sqrt(det ratio) = var / var'
    v, u = torch.meshgrid(
        torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64), indexing="ij"
    )
    d2 = (u + 0.5 - cx) ** 2 + (v + 0.5 - cy) ** 2
    alpha = (o * torch.exp(-0.5 * d2 / var_dilated)).clamp(max=constants.ALPHA_MAX)
    return torch.where(alpha >= constants.ALPHA_MIN, alpha, torch.zeros_like(alpha))


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("antialiased", [False, True])
@pytest.mark.parametrize("scale,opacity", [(0.01, 0.8), (0.002, 0.6), (0.05, 1.0)])
def test_isotropic_gaussian_facing_camera_is_an_analytic_2d_gaussian(backend, antialiased, scale, opacity):
    width, height, f, cx, cy, depth = 40, 30, 120.0, 17.3, 14.6, 2.0
    dtype = torch.float64 if backend == "torch" else torch.float32
    params = _one_gaussian(scale, depth, opacity, dtype)
    K = torch.tensor([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]], dtype=dtype)
    image, alpha, info = rasterize(
        *params, torch.eye(4, dtype=dtype), K, width, height, backend=backend, antialiased=antialiased
    )
    expected = _analytic_alpha(width, height, f, cx, cy, scale, depth, opacity, antialiased)
    tol = 1e-10 if dtype == torch.float64 else 2e-6
    assert torch.allclose(alpha[..., 0].double(), expected, atol=tol, rtol=0)
    colour = params[4][0].double()
    assert torch.allclose(image.double(), expected[..., None] * colour, atol=tol, rtol=0)
    assert info["means2d"].detach().double()[0].tolist() == pytest.approx([cx, cy], abs=1e-5)
    var = (f * scale / depth) ** 2 + constants.LOW_PASS_EPS2D
    conic = info["conics"].detach().double()[0]
    assert conic.tolist() == pytest.approx([1 / var, 0.0, 1 / var], rel=1e-5, abs=1e-9)


@pytest.mark.parametrize("backend", BACKENDS)
def test_expected_depth_of_a_single_gaussian_is_its_camera_z(backend):
    dtype = torch.float64 if backend == "torch" else torch.float32
    params = _one_gaussian(0.02, 2.5, 0.9, dtype)
    K = torch.tensor([[80.0, 0.0, 16.0], [0.0, 80.0, 12.0], [0.0, 0.0, 1.0]], dtype=dtype)
    _, alpha, info = rasterize(
        *params, torch.eye(4, dtype=dtype), K, 32, 24, backend=backend, render_depth=True
    )
    covered = alpha[..., 0] > 0
    assert covered.sum() > 20
    assert torch.allclose(
        info["depth"][..., 0][covered].double(), torch.tensor(2.5, dtype=torch.float64), atol=1e-5
    )
    assert (info["depth"][~covered] == 0).all()
    _, alpha_acc, info_acc = rasterize(
        *params,
        torch.eye(4, dtype=dtype),
        K,
        32,
        24,
        backend=backend,
        render_depth=True,
        depth_mode="accumulated",
    )
    assert torch.allclose(info_acc["depth"], 2.5 * alpha_acc, atol=1e-5)


@pytest.mark.parametrize("backend", BACKENDS)
def test_two_gaussians_composite_front_to_back(backend):
    """Front one at z=2 (opacity a1), back one at z=4 (a2): colour = c1 a1 + c2 a2 (1 - a1)."""
    dtype = torch.float64 if backend == "torch" else torch.float32
    means = torch.tensor([[0.0, 0.0, 4.0], [0.0, 0.0, 2.0]], dtype=dtype)  # back one listed first
    quats = torch.tensor([[1.0, 0, 0, 0], [1.0, 0, 0, 0]], dtype=dtype)
    scales = torch.tensor([[0.4] * 3, [0.2] * 3], dtype=dtype)  # equal screen size: 0.1 rad
    opacities = torch.tensor([0.7, 0.6], dtype=dtype)
    colors = torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]], dtype=dtype)
    K = torch.tensor([[100.0, 0.0, 10.0], [0.0, 100.0, 10.0], [0.0, 0.0, 1.0]], dtype=dtype)
    image, alpha, _ = rasterize(
        means,
        quats,
        scales,
        opacities,
        colors,
        torch.eye(4, dtype=dtype),
        K,
        20,
        20,
        background=torch.tensor([0.0, 0.0, 1.0], dtype=dtype),
        backend=backend,
    )
    var = 10.0**2 + constants.LOW_PASS_EPS2D
    g = math.exp(-0.5 * 0.5 / var)  # pixel (10, 10) centre is 0.5 px from the mean in x and y
    a1, a2 = 0.6 * g, 0.7 * g
    expected = torch.tensor([a1, a2 * (1 - a1), (1 - a1) * (1 - a2)], dtype=torch.float64)
    assert image[10, 10].double().tolist() == pytest.approx(expected.tolist(), abs=1e-6)
    assert alpha[10, 10, 0].item() == pytest.approx(1 - (1 - a1) * (1 - a2), abs=1e-6)


def test_opaque_stack_stops_when_transmittance_would_reach_the_threshold():
    """Ten opaque layers: each blends alpha ALPHA_MAX (0.999, gsplat's clamp) until the next would
    take T to 1e-4 or below (gsplat's `next_T <= 1e-4f`): T 1 -> 0.001, then the second layer
    (T 1e-6) is not blended."""
    n = 10
    means = torch.stack([torch.tensor([0.0, 0.0, 2.0 + 0.1 * i]) for i in range(n)]).double()
    quats = torch.tensor([[1.0, 0, 0, 0]] * n, dtype=torch.float64)
    scales = torch.full((n, 3), 1.0, dtype=torch.float64)  # huge: alpha clamps to ALPHA_MAX
    opacities = torch.ones(n, dtype=torch.float64)
    colors = torch.eye(n, dtype=torch.float64)
    K = torch.tensor([[50.0, 0.0, 4.0], [0.0, 50.0, 4.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    for backend in BACKENDS:
        for dtype in (torch.float32, torch.float64) if backend == "torch" else (torch.float32,):
            image, alpha, _ = rasterize(
                means.to(dtype),
                quats.to(dtype),
                scales.to(dtype),
                opacities.to(dtype),
                colors.to(dtype),
                torch.eye(4, dtype=dtype),
                K.to(dtype),
                8,
                8,
                backend=backend,
            )
            # The same rule in the working precision.
            keep = 1.0 - torch.tensor(constants.ALPHA_MAX, dtype=dtype)
            t2 = keep * keep
            second = bool(t2 > torch.tensor(constants.TRANSMITTANCE_MIN, dtype=dtype))
            assert not second
            expected = [
                constants.ALPHA_MAX,
                constants.ALPHA_MAX * (1 - constants.ALPHA_MAX) if second else 0.0,
            ]
            pix = image[4, 4].double()
            assert pix[:2].tolist() == pytest.approx(expected, abs=1e-6), (backend, dtype)
            assert pix[2:].abs().max().item() == 0.0
            assert 1 - alpha[4, 4, 0].item() == pytest.approx(float(t2 if second else keep), rel=1e-5)


def test_gradcheck_torch_reference_float64():
    torch.manual_seed(3)
    n, width, height = 3, 12, 10
    means = torch.tensor([[0.05, -0.02, 2.0], [-0.1, 0.05, 2.5], [0.08, 0.1, 3.0]], dtype=torch.float64)
    quats = torch.randn(n, 4, dtype=torch.float64)
    scales = torch.tensor([[0.05, 0.03, 0.04], [0.06, 0.05, 0.02], [0.04, 0.07, 0.05]], dtype=torch.float64)
    opacities = torch.tensor([0.6, 0.5, 0.7], dtype=torch.float64)
    colors = torch.rand(n, 3, dtype=torch.float64)
    K = torch.tensor([[40.0, 0.0, 6.1], [0.0, 40.0, 4.9], [0.0, 0.0, 1.0]], dtype=torch.float64)
    weights = torch.rand(height, width, 3, dtype=torch.float64)
    background = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)

    for antialiased in (False, True):

        def loss(m, q, s, o, c, bg, antialiased=antialiased):
            image, alpha, info = rasterize(
                m,
                q,
                s,
                o,
                c,
                torch.eye(4, dtype=torch.float64),
                K,
                width,
                height,
                background=bg,
                backend="torch",
                antialiased=antialiased,
                render_depth=True,
            )
            return (image * weights).sum() + alpha.sum() * 0.3 + info["depth"].sum() * 0.01

        inputs = [
            t.clone().requires_grad_(True) for t in (means, quats, scales, opacities, colors, background)
        ]
        assert torch.autograd.gradcheck(loss, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)
