"""Numerical stability at the extremes, on every backend this machine has: tiny and huge
scales, Gaussians behind the camera / on the near plane / across the border, opacity 0 and 1,
zero and unnormalised quaternions, NaN/inf inputs, 0 / 1 / 1M Gaussians, 1x1 to 4096x4096
images. Outputs and gradients must stay finite; memory must stay bounded."""

from __future__ import annotations

import math

import pytest
import torch

from stg_node.splat import constants, rasterize
from stg_node.splat.api import cpu_backend_status, cuda_backend_status
from stg_node.splat.scenes import front_camera, person_sized_scene


def _backend_params():
    params = [pytest.param(("torch", "cpu"), id="torch")]
    if cpu_backend_status() is None:
        params.append(pytest.param(("cpu", "cpu"), id="cpu"))
    params.append(pytest.param(("cuda", "cuda"), id="cuda", marks=pytest.mark.gpu))
    return params


@pytest.fixture(params=_backend_params())
def backend(request):
    name, device = request.param
    if name == "cuda" and cuda_backend_status() is not None:
        pytest.skip(f"cuda backend unavailable: {cuda_backend_status()}")
    return name, device


def _camera(width=32, height=24, f=40.0, device="cpu"):
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], device=device)
    return torch.eye(4, device=device), K


def _gaussians(means, scales=None, opacities=None, quats=None, colors=None, device="cpu"):
    means = torch.as_tensor(means, dtype=torch.float32).reshape(-1, 3)
    n = means.shape[0]
    scales = torch.full((n, 3), 0.05) if scales is None else torch.as_tensor(scales, dtype=torch.float32)
    scales = scales.reshape(n, scales.numel() // max(n, 1) or 3).expand(n, 3).contiguous()
    opacities = (
        torch.full((n,), 0.8) if opacities is None else torch.as_tensor(opacities, dtype=torch.float32)
    )
    quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1) if quats is None else torch.as_tensor(quats).float()
    colors = torch.rand(n, 3, generator=torch.Generator().manual_seed(n)) if colors is None else colors
    return [t.to(device) for t in (means, quats, scales, opacities.reshape(n), colors)]


def _render_and_backprop(backend, params, viewmat, K, width, height, **options):
    name, device = backend
    params = [p.detach().clone().requires_grad_(True) for p in params]
    image, alpha, info = rasterize(*params, viewmat, K, width, height, backend=name, **options)
    assert image.shape == (height, width, params[4].shape[1])
    assert alpha.shape == (height, width, 1)
    assert torch.isfinite(image).all() and torch.isfinite(alpha).all()
    (
        (image * torch.linspace(0.1, 1, image.numel(), device=device).reshape(image.shape)).sum()
        + alpha.sum()
    ).backward()
    for p in params:
        assert p.grad is not None and torch.isfinite(p.grad).all()
    return image.detach(), alpha.detach(), info, [p.grad for p in params]


def test_scales_from_1e_minus_6_to_1e3(backend):
    device = backend[1]
    viewmat, K = _camera(device=device)
    scales = torch.logspace(-6, 3, 10)
    means = torch.stack([torch.tensor([0.05 * (i - 5), 0.02 * (i % 3), 0.5 + 0.3 * i]) for i in range(10)])
    params = _gaussians(means, scales[:, None], device=device)
    for antialiased in (False, True):
        image, alpha, info, _ = _render_and_backprop(
            backend, params, viewmat, K, 32, 24, antialiased=antialiased
        )
        assert alpha.max() > 0.5
        assert (info["radii"] >= 0).all()


def test_a_huge_gaussian_covers_the_image_evenly(backend):
    viewmat, K = _camera(device=backend[1])
    params = _gaussians([[0.0, 0.0, 2.0]], [[1e3]], [0.7], device=backend[1])
    _, alpha, info, _ = _render_and_backprop(backend, params, viewmat, K, 32, 24)
    assert torch.allclose(alpha, torch.full_like(alpha, 0.7), atol=1e-4)
    assert info["radii"].max() <= constants.RADIUS_REPORT_MAX


def test_a_tiny_gaussian_is_the_low_pass_filter(backend):
    """scale 1e-6: the 2D covariance is the 0.3 px^2 dilation alone."""
    viewmat, K = _camera(device=backend[1])
    params = _gaussians([[0.0, 0.0, 2.0]], [[1e-6]], [0.9], device=backend[1])
    _, alpha, _, _ = _render_and_backprop(backend, params, viewmat, K, 32, 24)
    # The mean projects to (16, 12): the 4 pixel centres around it are 0.5 px away per axis.
    expected = 0.9 * math.exp(-0.5 * 0.5 / constants.LOW_PASS_EPS2D)
    assert alpha[11:13, 15:17].flatten().tolist() == pytest.approx([expected] * 4, rel=1e-4)
    # Antialiased: the compensation sqrt(det/det_dilated) ~ 0 removes it entirely.
    _, alpha_aa, info, _ = _render_and_backprop(backend, params, viewmat, K, 32, 24, antialiased=True)
    assert alpha_aa.max() == 0 and not info["visible"].any()


def test_behind_the_camera_is_culled(backend):
    viewmat, K = _camera(device=backend[1])
    params = _gaussians(
        [[0.0, 0.0, -2.0], [0.1, 0.0, -0.001], [0.0, 0.0, 0.0]], [[0.5]] * 3, device=backend[1]
    )
    bg = torch.tensor([0.1, 0.2, 0.3], device=backend[1])
    image, alpha, info, grads = _render_and_backprop(backend, params, viewmat, K, 32, 24, background=bg)
    assert alpha.max() == 0
    assert torch.allclose(image, bg.expand_as(image))
    assert not info["visible"].any()
    assert all(g.abs().max() == 0 for g in grads)


def test_on_the_near_plane_is_kept_and_just_before_it_is_culled(backend):
    viewmat, K = _camera(device=backend[1])
    near = constants.NEAR_PLANE
    params = _gaussians([[0.0, 0.0, near], [0.0, 0.0, near * 0.999]], [[1e-4]] * 2, device=backend[1])
    _, alpha, info, _ = _render_and_backprop(backend, params, viewmat, K, 32, 24)
    assert info["visible"].tolist() == [True, False]
    assert alpha.max() > 0.4
    # A custom near plane moves the cut.
    _, _, info2, _ = _render_and_backprop(backend, params, viewmat, K, 32, 24, near_plane=0.5)
    assert not info2["visible"].any()


def test_straddling_the_image_border(backend):
    """Centre 3 px left of the image: only its right half shows, exactly as the 2D Gaussian."""
    viewmat, K = _camera(device=backend[1])
    f, depth, scale = 40.0, 2.0, 0.25  # 5 px standard deviation
    x = (-3.0 - 16.0) / f * depth  # pixel u = -3
    # Flat along z, so the off-axis perspective term of the EWA Jacobian vanishes.
    params = _gaussians([[x, 0.0, depth]], [[scale, scale, 1e-6]], [0.6], device=backend[1])
    _, alpha, info, _ = _render_and_backprop(backend, params, viewmat, K, 32, 24)
    assert info["visible"].all()
    var = (f * scale / depth) ** 2 + constants.LOW_PASS_EPS2D
    v, u = torch.meshgrid(torch.arange(24.0), torch.arange(32.0), indexing="ij")
    expected = 0.6 * torch.exp(-0.5 * ((u + 0.5 + 3.0) ** 2 + (v + 0.5 - 12.0) ** 2) / var)
    expected = torch.where(expected >= constants.ALPHA_MIN, expected, torch.zeros_like(expected))
    assert torch.allclose(alpha[..., 0].cpu(), expected, atol=2e-5)
    assert alpha[:, 0].max() > 0.3 and alpha[:, -1].max() == 0


def test_opacity_zero_and_one(backend):
    """Opacity 0 is culled; opacity 1 gives min(ALPHA_MAX, exp(-sigma)): gsplat's clamp, on
    every backend (float32 and gsplat's fast exp agree to ~1e-7 here: tolerance 2e-6)."""
    viewmat, K = _camera(device=backend[1])
    f, depth = 40.0, 2.0
    # A 10 px Gaussian centred on a pixel corner, (22, 12): its 4 nearest pixel centres are
    # 0.5 px away per axis, where exp(-sigma) = 0.9975 lies between 0.99 and ALPHA_MAX. Flat
    # along z, so the off-axis term of the EWA Jacobian vanishes.
    scales = [[0.05, 0.05, 0.05], [0.5, 0.5, 1e-6]]
    params = _gaussians([[0.0, 0.0, depth], [0.3, 0.0, depth]], scales, [0.0, 1.0], device=backend[1])
    _, alpha, info, grads = _render_and_backprop(backend, params, viewmat, K, 32, 24)
    assert info["visible"].tolist() == [False, True]
    var = (f * 0.5 / depth) ** 2 + constants.LOW_PASS_EPS2D
    peak = math.exp(-0.5 * 0.5 / var)
    assert 0.99 < peak < constants.ALPHA_MAX
    assert alpha[11:13, 21:23].flatten().tolist() == pytest.approx([peak] * 4, abs=2e-6)
    assert alpha.max().item() == pytest.approx(peak, abs=2e-6)
    assert grads[3][0] == 0  # an invisible Gaussian gets no gradient
    # A 20 px Gaussian: exp(-sigma) > ALPHA_MAX near its centre, so alpha clamps there.
    wide = _gaussians([[0.3, 0.0, depth]], [[1.0, 1.0, 1e-6]], [1.0], device=backend[1])
    _, alpha_wide, _, _ = _render_and_backprop(backend, wide, viewmat, K, 32, 24)
    assert alpha_wide.max().item() == pytest.approx(constants.ALPHA_MAX, abs=1e-7)
    assert (alpha_wide > constants.ALPHA_MAX - 1e-7).sum() >= 4


def test_transmittance_stop_at_exactly_the_threshold(backend):
    """gsplat stops a pixel when the next Gaussian would take T to 1e-4 *or below* (exclusive:
    that one is not blended). Two Gaussians centred on a pixel centre (sigma = 0, so alpha =
    opacity exactly) with float32 opacities chosen so that (1 - a1)(1 - a2) rounds to exactly
    float32(1e-4): (1 - a1) = 1593856 / 2^24, (1 - a2) = 17660 / 2^24, product 2^48 * 1e-4f."""
    device = backend[1]
    a1, a2 = 1 - 1593856 / 2**24, 1 - 17660 / 2**24
    T1 = torch.tensor(1.0) - torch.tensor(a1)
    assert T1 * (torch.tensor(1.0) - torch.tensor(a2)) == torch.tensor(constants.TRANSMITTANCE_MIN)
    K = torch.tensor([[20.0, 0.0, 4.5], [0.0, 20.0, 4.5], [0.0, 0.0, 1.0]], device=device)
    colors = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    params = _gaussians(
        [[0.0, 0.0, 2.0], [0.0, 0.0, 3.0]], [[0.01]] * 2, [a1, a2], colors=colors, device=device
    )
    image, alpha, _, _ = _render_and_backprop(backend, params, torch.eye(4, device=device), K, 9, 9)
    assert image[4, 4].tolist() == [pytest.approx(a1, abs=1e-7), 0.0, 0.0]
    assert alpha[4, 4, 0].item() == pytest.approx(a1, abs=1e-7)


def test_zero_and_unnormalised_quaternions(backend):
    device = backend[1]
    viewmat, K = _camera(device=device)
    means = [[-0.2, 0.0, 2.0], [0.2, 0.05, 2.5]]
    scales = [[0.08, 0.02, 0.04], [0.03, 0.09, 0.02]]
    q = torch.tensor([[0.9, 0.3, -0.2, 0.1], [0.2, -0.5, 0.4, 0.7]])
    q_unit = q / q.norm(dim=1, keepdim=True)
    ref = _render_and_backprop(
        backend, _gaussians(means, scales, quats=q_unit, device=device), viewmat, K, 32, 24
    )
    scaled = _render_and_backprop(
        backend, _gaussians(means, scales, quats=q * 7.3, device=device), viewmat, K, 32, 24
    )
    assert torch.allclose(ref[0], scaled[0], atol=1e-6)
    # Gradients w.r.t. q scale by 1/|q| and are tangent to the unit sphere.
    norms = (q * 7.3).norm(dim=1, keepdim=True).to(device)
    assert torch.allclose(scaled[3][1] * norms, ref[3][1], rtol=1e-3, atol=1e-5)
    assert torch.allclose(
        (ref[3][1] * q_unit.to(device)).sum(dim=1), torch.zeros(2, device=device), atol=1e-4
    )
    zero = _render_and_backprop(
        backend, _gaussians(means, scales, quats=torch.zeros(2, 4), device=device), viewmat, K, 32, 24
    )
    identity = _render_and_backprop(
        backend,
        _gaussians(means, scales, quats=torch.tensor([[1.0, 0, 0, 0]] * 2), device=device),
        viewmat,
        K,
        32,
        24,
    )
    assert torch.allclose(zero[0], identity[0], atol=1e-6)


@pytest.mark.parametrize(
    "name", ["means", "quats", "scales", "opacities", "colors", "viewmat", "K", "background"]
)
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_nan_or_inf_in_any_input_is_a_clear_error(backend, name, bad):
    device = backend[1]
    viewmat, K = _camera(device=device)
    means, quats, scales, opacities, colors = _gaussians([[0.0, 0.0, 2.0], [0.1, 0.1, 3.0]], device=device)
    args = dict(
        means=means,
        quats=quats,
        scales=scales,
        opacities=opacities,
        colors=colors,
        viewmat=viewmat,
        K=K,
        background=torch.zeros(3, device=device),
    )
    poisoned = args[name].clone()
    poisoned.view(-1)[-1] = bad
    args[name] = poisoned
    with pytest.raises(ValueError, match=f"^{name} contains non-finite values"):
        rasterize(
            args["means"],
            args["quats"],
            args["scales"],
            args["opacities"],
            args["colors"],
            args["viewmat"],
            args["K"],
            32,
            24,
            background=args["background"],
            backend=backend[0],
        )


@pytest.mark.parametrize("n", [0, 1])
def test_zero_and_one_gaussian(backend, n):
    device = backend[1]
    viewmat, K = _camera(device=device)
    params = _gaussians(torch.tensor([[0.0, 0.0, 2.0]])[:n], device=device)
    bg = torch.tensor([0.3, 0.3, 0.3], device=device)
    image, alpha, info, grads = _render_and_backprop(backend, params, viewmat, K, 32, 24, background=bg)
    assert info["means2d"].shape == (n, 2) and info["radii"].shape == (n, 2)
    assert [tuple(g.shape) for g in grads] == [(n, 3), (n, 4), (n, 3), (n,), (n, 3)]
    if n == 0:
        assert alpha.max() == 0 and torch.allclose(image, bg.expand_as(image))
    else:
        assert alpha.max() > 0.5 and info["visible"].all()


def test_nothing_visible_renders_the_background(backend):
    """Every Gaussian culled, each by another rule (behind, beyond the far plane, off-screen,
    opacity below 1/255): the background, alpha 0, zero and finite gradients, no intersection."""
    device = backend[1]
    viewmat, K = _camera(device=device)
    means = [[0.0, 0.0, -1.0], [0.0, 0.0, 50.0], [3.0, 0.0, 1.0], [0.0, -2.0, 1.0], [0.0, 0.0, 2.0]]
    opacities = [0.9, 0.9, 0.9, 0.9, 0.5 / 255]
    params = _gaussians(means, [[0.05]] * 5, opacities, device=device)
    bg = torch.tensor([0.3, 0.5, 0.7], device=device)
    image, alpha, info, grads = _render_and_backprop(
        backend, params, viewmat, K, 32, 24, background=bg, far_plane=10.0
    )
    assert alpha.max() == 0 and torch.equal(image, bg.expand_as(image))
    assert not info["visible"].any() and not info["radii"].any() and info["n_intersections"] == 0
    assert all(not g.any() for g in grads)


@pytest.mark.parametrize("size", [(0, 24), (32, 0), (0, 0)])
def test_zero_area_images_are_empty_backgrounds(backend, size):
    width, height = size
    device = backend[1]
    viewmat, K = _camera(device=device)
    params = _gaussians([[0.0, 0.0, 2.0], [0.1, 0.0, 3.0]], device=device)
    bg = torch.tensor([0.3, 0.5, 0.7], device=device)
    image, alpha, info, grads = _render_and_backprop(
        backend, params, viewmat, K, width, height, background=bg, render_depth=True
    )
    assert info["depth"].shape == (height, width, 1)
    assert not info["visible"].any() and info["means2d"].shape == (2, 2)
    assert all(not g.any() for g in grads)


@pytest.mark.parametrize("size", [(1, 1), (1, 7), (9, 1), (17, 33)])
def test_small_and_odd_image_sizes(backend, size):
    width, height = size
    device = backend[1]
    K = torch.tensor([[10.0, 0.0, width / 2], [0.0, 10.0, height / 2], [0.0, 0.0, 1.0]], device=device)
    params = _gaussians([[0.0, 0.0, 1.0], [0.02, -0.03, 1.5], [5.0, 5.0, 1.0]], [[0.05]] * 3, device=device)
    _, alpha, info, _ = _render_and_backprop(backend, params, torch.eye(4, device=device), K, width, height)
    assert alpha.max() > 0.3
    assert not info["visible"][2]  # far outside the tiny image


def _big_image_case(device):
    width = height = 4096
    viewmat, K = front_camera(width, height)
    scene = person_sized_scene(2000, seed=1)
    return [t.to(device) for t in scene.params()], viewmat.to(device), K.to(device), width, height


def test_4096_squared_image(backend):
    if backend[0] == "torch":
        pytest.skip("the torch reference at 4096x4096 runs in the slow suite")
    params, viewmat, K, width, height = _big_image_case(backend[1])
    _, alpha, info, _ = _render_and_backprop(backend, params, viewmat, K, width, height)
    assert alpha.mean() > 0.03 and info["visible"].sum() > 1900


@pytest.mark.slow
def test_4096_squared_image_torch_reference():
    params, viewmat, K, width, height = _big_image_case("cpu")
    _, alpha, info, _ = _render_and_backprop(("torch", "cpu"), params, viewmat, K, width, height)
    assert alpha.mean() > 0.03


def _million_case(device):
    scene = person_sized_scene(1_000_000, seed=2, min_scale=0.001, max_scale=0.01)
    viewmat, K = front_camera(128, 128)
    return [t.to(device) for t in scene.params()], viewmat.to(device), K.to(device)


def test_one_million_gaussians(backend):
    if backend[0] == "torch":
        pytest.skip("the torch reference with 1M Gaussians runs in the slow suite")
    params, viewmat, K = _million_case(backend[1])
    _, alpha, info, _ = _render_and_backprop(backend, params, viewmat, K, 128, 128)
    assert info["visible"].sum() > 900_000
    assert alpha.mean() > 0.1


@pytest.mark.slow
def test_one_million_gaussians_torch_reference():
    params, viewmat, K = _million_case("cpu")
    _, alpha, info, _ = _render_and_backprop(("torch", "cpu"), params, viewmat, K, 128, 128)
    assert alpha.mean() > 0.1


def test_intersection_count_is_int64_and_chunked(backend):
    """40k screen-filling Gaussians on 4096^2 tiles: 2.6e9 intersections, beyond int32."""
    if backend[0] != "cpu":
        pytest.skip("counts the C++ binner directly")
    from stg_node.splat.build import load_kernels

    n, width, height = 40_000, 4096, 4096
    bbox = torch.tensor([[0, width - 1, 0, height - 1]], dtype=torch.int32).repeat(n, 1)
    visible = torch.ones(n, dtype=torch.bool)
    total, chunks = (
        load_kernels()
        .ops.count_intersections(bbox, visible, width, height, constants.MAX_INTERSECTIONS_PER_CHUNK)
        .tolist()
    )
    assert total == n * (width // 16) * (height // 16) > 2**31
    assert chunks == math.ceil(total / constants.MAX_INTERSECTIONS_PER_CHUNK)


def test_memory_stays_bounded_when_every_gaussian_covers_every_tile(backend):
    """Many full-screen Gaussians: the cpu backend splits the work into bounded chunks and the
    image does not depend on the chunking."""
    if backend[0] != "cpu":
        pytest.skip("chunking is a property of the cpu backend")
    n = 300
    viewmat, K = _camera(128, 96, f=100.0)
    gen = torch.Generator().manual_seed(0)
    means = torch.cat([torch.rand(n, 2, generator=gen) * 0.2 - 0.1, torch.rand(n, 1, generator=gen) + 1.0], 1)
    params = _gaussians(means, torch.full((n, 1), 2.0), torch.full((n,), 0.02))
    image1, _, info1, _ = _render_and_backprop(backend, params, viewmat, K, 128, 96)
    assert info1["stats"]["forward"]["n_intersections"] == info1["n_intersections"] == n * 8 * 6
    image2, _, info2, _ = _render_and_backprop(backend, params, viewmat, K, 128, 96, max_intersections=1000)
    assert info2["stats"]["forward"]["n_chunks"] >= 14
    assert torch.equal(image1, image2)
