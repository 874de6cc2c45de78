"""The C++ SSIM kernel (stg_node.splat.image_ops.ssim) against independent truth: scikit-image's
structural_similarity and autograd through the torch implementation in float64."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from skimage import data as skdata
from skimage.metrics import structural_similarity
from skimage.transform import resize

from stg_node.avatar import losses
from stg_node.splat import build, image_ops

SIZES = [(11, 11), (12, 37), (37, 12), (420, 200)]


pytestmark = pytest.mark.usefixtures("cpu_kernels")  # skips where the kernels cannot build


def random_pair(h, w, c=3, seed=0):
    gen = torch.Generator().manual_seed(seed)
    return torch.rand(h, w, c, generator=gen, dtype=torch.float64), torch.rand(
        h, w, c, generator=gen, dtype=torch.float64
    )


def natural_pair(h, w, seed=0):
    """A photograph (resized to h x w) and a render-like estimate of it: blurred, shifted by a
    pixel, noisy, with a flat black border (zero-variance windows) as around a person crop."""
    photo = resize(skdata.astronaut()[40:460, 150:350] / 255.0, (h, w), anti_aliasing=True)
    target = torch.from_numpy(photo).to(torch.float64)
    gen = torch.Generator().manual_seed(seed)
    render = 0.5 * (target + torch.roll(target, 1, dims=1))
    render = (render + 0.02 * torch.randn(render.shape, generator=gen, dtype=torch.float64)).clamp(0, 1)
    edge = max(1, min(h, w) // 8)
    for image in (target, render):
        image[:edge] = 0.0
        image[:, -edge:] = 0.0
    return render, target


def pairs():
    """(name, a, b): random and natural pairs at each size, odd channel counts, an identical pair,
    and flat images (every window has zero variance)."""
    for h, w in SIZES:
        yield f"random-{h}x{w}", *random_pair(h, w, seed=h * 1000 + w)
        yield f"natural-{h}x{w}", *natural_pair(h, w, seed=h + w)
    yield "random-1ch", *random_pair(40, 23, c=1, seed=7)
    yield "random-5ch", *random_pair(23, 40, c=5, seed=8)
    a, _ = natural_pair(64, 48)
    yield "identical", a, a.clone()
    yield "flat", *flat_pair()


def flat_pair():
    shape = (20, 30, 3)
    return torch.full(shape, 0.25, dtype=torch.float64), torch.full(shape, 0.75, dtype=torch.float64)


PAIRS = list(pairs())
PRECISE_PAIRS = [p for p in PAIRS if p[0] != "flat"]  # flat: test_flat_images_are_as_exact_as_float32


def kernel_value_and_grad(a, b, scale=1.0):
    leaf = a.detach().to(torch.float32).requires_grad_(True)
    value = image_ops.ssim(leaf, b.to(torch.float32))
    (scale * value).backward()
    return value.detach(), leaf.grad


def oracle_value_and_grad(a, b):
    leaf = a.detach().to(torch.float64).requires_grad_(True)
    value = losses.ssim_torch(leaf, b.to(torch.float64))
    value.backward()
    return value.detach(), leaf.grad


def skimage_ssim(a, b):
    return structural_similarity(
        a.numpy(),
        b.numpy(),
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
        data_range=1.0,
        channel_axis=2,
    )


@pytest.mark.parametrize("name,a,b", PRECISE_PAIRS, ids=[p[0] for p in PRECISE_PAIRS])
def test_value_matches_torch_and_scikit_image(name, a, b):
    value, _ = kernel_value_and_grad(a, b)
    assert value.dtype == torch.float32 and value.dim() == 0
    oracle, _ = oracle_value_and_grad(a, b)
    skimage_value = skimage_ssim(a, b)
    # scikit-image filters the whole image and averages S over it less a 5 px border: our valid region.
    assert abs(float(oracle) - skimage_value) < 1e-10
    assert abs(float(value) - skimage_value) < 1e-5


@pytest.mark.parametrize("name,a,b", PRECISE_PAIRS, ids=[p[0] for p in PRECISE_PAIRS])
def test_gradient_matches_autograd_through_torch(name, a, b):
    _, grad = kernel_value_and_grad(a, b)
    _, oracle = oracle_value_and_grad(a, b)
    assert grad.shape == a.shape and grad.dtype == torch.float32
    error = (grad.double() - oracle).norm()
    if name == "identical":  # S is at its maximum: the gradient vanishes (to float32 rounding)
        _, perturbed = oracle_value_and_grad(a, (b + 0.01 * torch.sin(40 * a)).clamp(0, 1))
        assert float(oracle.abs().max()) < 1e-12
        assert float(grad.abs().max()) < 1e-3 * float(perturbed.abs().max())
        return
    assert float(error / oracle.norm()) < 1e-4
    assert float((grad.double() - oracle).abs().max() / oracle.abs().max()) < 1e-3


def test_flat_images_are_as_exact_as_float32():
    """On a flat bright window var = E[a^2] - mu^2 = 0 is a difference of two numbers near 0.56,
    each rounded to float32 (6e-8), which C2 = 9e-4 turns into ~1e-4 of S: the torch path in
    float32 errs the same way; only float64 statistics would do better."""
    a, b = flat_pair()
    value, grad = kernel_value_and_grad(a, b)
    leaf = a.float().requires_grad_(True)
    torch32 = losses.ssim_torch(leaf, b.float())
    torch32.backward()
    torch32 = torch32.detach()
    exact = skimage_ssim(a, b)
    assert abs(float(value) - float(torch32)) < 1e-6
    assert abs(float(value) - exact) < 2e-4
    _, oracle = oracle_value_and_grad(a, b)
    assert float((grad.double() - oracle).norm() / oracle.norm()) < 5e-4  # measured 9e-5, as torch's
    assert float((leaf.grad.double() - oracle).norm() / oracle.norm()) < 5e-4
    dark = 0.1 * a  # squares near 6e-4: the rounding is 100x smaller
    assert abs(float(kernel_value_and_grad(dark, 0.1 * b)[0]) - skimage_ssim(dark, 0.1 * b)) < 1e-5


def test_upstream_gradient_scales_the_result():
    a, b = natural_pair(30, 26)
    _, once = kernel_value_and_grad(a, b)
    _, scaled = kernel_value_and_grad(a, b, scale=-3.0)
    torch.testing.assert_close(scaled, -3.0 * once, rtol=1e-6, atol=0)


def test_thread_count_does_not_change_the_result():
    a, b = natural_pair(97, 61)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        v1, g1 = kernel_value_and_grad(a, b)
        torch.set_num_threads(2)
        v2, g2 = kernel_value_and_grad(a, b)
    finally:
        torch.set_num_threads(before)
    assert torch.equal(v1, v2) and torch.equal(g1, g2)


def test_non_contiguous_and_float64_inputs():
    a, b = natural_pair(40, 50)
    value, grad = kernel_value_and_grad(a, b)
    # A channel-first view, permuted back: not contiguous.
    leaf = a.to(torch.float32).permute(2, 0, 1).contiguous().requires_grad_(True)
    value_nc = image_ops.ssim(leaf.permute(1, 2, 0), b.to(torch.float32).permute(2, 0, 1).permute(1, 2, 0))
    value_nc.backward()
    assert torch.equal(value_nc.detach(), value)
    assert torch.equal(leaf.grad.permute(1, 2, 0), grad)
    # float64 in: computed in float32, value and gradient handed back in float64.
    leaf64 = a.clone().requires_grad_(True)
    value64 = image_ops.ssim(leaf64, b)
    value64.backward()
    assert value64.dtype == torch.float64 and leaf64.grad.dtype == torch.float64
    assert value64.detach().to(torch.float32) == value


def test_forward_without_gradient_makes_no_derivative_maps(monkeypatch):
    a, b = random_pair(30, 30)
    ops = build.load_kernels().ops
    asked = []

    class Spy:
        def ssim_fwd(self, *args):
            asked.append(args[5])  # want_grad
            return ops.ssim_fwd(*args)

    monkeypatch.setattr(image_ops, "load_kernels", lambda: type("K", (), {"ops": Spy()})())
    leaf = a.float().requires_grad_(True)
    with torch.no_grad():
        value = image_ops.ssim(leaf, b.float())
    image_ops.ssim(a.float(), b.float())
    assert asked == [False, False]
    assert not value.requires_grad
    assert abs(float(value) - float(losses.ssim_torch(a, b))) < 1e-5
    assert image_ops.ssim(leaf, b.float()).requires_grad and asked[-1] is True


@pytest.mark.parametrize(
    "shape_a,shape_b,message",
    [
        ((10, 30, 3), (10, 30, 3), "at least 11x11"),
        ((30, 10, 3), (30, 10, 3), "at least 11x11"),
        ((11, 11, 3), (11, 12, 3), "one shape"),
        ((20, 20), (20, 20), r"\(H, W, C\)"),
        ((20, 20, 0), (20, 20, 0), "at least one channel"),
    ],
)
def test_bad_shapes_raise(shape_a, shape_b, message):
    with pytest.raises(ValueError, match=message):
        image_ops.ssim(torch.zeros(shape_a), torch.zeros(shape_b))


def test_gradient_for_the_second_image_is_refused():
    a, b = random_pair(20, 20)
    with pytest.raises(ValueError, match="first image"):
        image_ops.ssim(a.float(), b.float().requires_grad_(True))
    # The loss takes the torch path instead and differentiates both.
    b32 = b.float().requires_grad_(True)
    losses.ssim(a.float(), b32).backward()
    assert b32.grad is not None and float(b32.grad.abs().sum()) > 0


def test_operator_checks_its_inputs():
    ops = build.load_kernels().ops
    a = torch.rand(20, 20, 3)
    assert ops.image_window() == image_ops.SSIM_WINDOW
    with pytest.raises(RuntimeError, match="11 taps"):
        ops.ssim_fwd(a, a, image_ops.gaussian_taps()[:7], 1e-4, 9e-4, False, 1)
    with pytest.raises(RuntimeError, match="at least 11x11"):
        ops.ssim_fwd(a[:10], a[:10], image_ops.gaussian_taps(), 1e-4, 9e-4, False, 1)
    with pytest.raises(RuntimeError, match="float32"):
        ops.ssim_fwd(a.double(), a.double(), image_ops.gaussian_taps(), 1e-4, 9e-4, False, 1)
    with pytest.raises(RuntimeError, match="derivative maps must be"):
        d = torch.zeros(9, 10, 3)
        ops.ssim_bwd(a, a, image_ops.gaussian_taps(), d, d, d, 1.0, 0.0, 1)


def test_loss_dispatch_and_fallback(monkeypatch):
    a, b = natural_pair(32, 40)
    a32, b32 = a.float(), b.float()
    assert image_ops.ssim_kernel_applies(a32, b32)
    assert not image_ops.ssim_kernel_applies(a, b)  # float64: the torch path keeps the precision
    calls = []
    real = image_ops.ssim
    monkeypatch.setattr(image_ops, "ssim", lambda x, y: calls.append(1) or real(x, y))
    kernel = losses.ssim(a32, b32)
    assert calls == [1]

    def unavailable():
        raise build.ExtensionUnavailable("no C++ compiler found (test)", reason="no-compiler")

    monkeypatch.setattr(image_ops, "load_kernels", unavailable)
    monkeypatch.setattr(image_ops, "_unavailable_logged", False)
    assert not image_ops.ssim_kernel_applies(a32, b32)
    fallback = losses.ssim(a32, b32)
    assert calls == [1]
    assert abs(float(kernel) - float(fallback)) < 1e-5


def test_taps_are_the_normalised_gaussian():
    taps = np.array(image_ops.gaussian_taps())
    x = np.arange(image_ops.SSIM_WINDOW) - image_ops.SSIM_WINDOW // 2
    expected = np.exp(-(x**2) / (2 * image_ops.SSIM_SIGMA**2))
    np.testing.assert_allclose(taps, expected / expected.sum(), rtol=1e-15)
    # scikit-image's window for sigma 1.5 (truncate 3.5) has the same radius.
    assert image_ops.SSIM_WINDOW == 2 * int(3.5 * image_ops.SSIM_SIGMA + 0.5) + 1


@pytest.mark.gpu
def test_cuda_tensors_take_the_torch_path():
    a, b = natural_pair(40, 30)
    a32, b32 = a.float(), b.float()
    assert not image_ops.ssim_kernel_applies(a32.cuda(), b32.cuda())
    leaf = a32.cuda().requires_grad_(True)
    value = losses.ssim(leaf, b32.cuda())
    value.backward()
    cpu_value, cpu_grad = kernel_value_and_grad(a, b)
    assert abs(float(value.detach()) - float(cpu_value)) < 1e-5
    assert float((leaf.grad.cpu() - cpu_grad).norm() / cpu_grad.norm()) < 1e-4


def l1_ssim_oracle(a, b, w_l1, w_ssim):
    leaf = a.detach().to(torch.float64).requires_grad_(True)
    l1 = (leaf - b.to(torch.float64)).abs().mean()
    value = losses.ssim_torch(leaf, b.to(torch.float64))
    (w_l1 * l1 + w_ssim * (1.0 - value)).backward()
    return l1.detach(), value.detach(), leaf.grad


@pytest.mark.parametrize("weights", [(0.8, 0.2), (1.0, 0.0), (0.0, 1.0)], ids=["both", "l1", "ssim"])
@pytest.mark.parametrize("name,a,b", PRECISE_PAIRS[:4], ids=[p[0] for p in PRECISE_PAIRS[:4]])
def test_l1_ssim_matches_torch_in_values_and_gradients(name, a, b, weights):
    """The fused photometric pair (image_ops.l1_ssim) against autograd in float64 through the
    torch L1 and SSIM, for the step's weighting and each term alone (an unused output's
    gradient arrives as None); ties (a == b at a pixel) get abs's zero gradient."""
    a = a.clone()
    a[3, :7] = b[3, :7]  # exact ties
    w_l1, w_ssim = weights
    leaf = a.detach().float().requires_grad_(True)
    l1, value = image_ops.l1_ssim(leaf, b.float())
    loss = (w_l1 * l1 if w_l1 else 0.0) + (w_ssim * (1.0 - value) if w_ssim else 0.0)
    loss.backward()
    ref_l1, ref_value, ref_grad = l1_ssim_oracle(a, b, w_l1, w_ssim)
    assert float(l1.detach()) == pytest.approx(float(ref_l1), rel=1e-6)
    assert float(value.detach()) == pytest.approx(float(ref_value), abs=1e-5)
    assert float((leaf.grad.double() - ref_grad).norm() / ref_grad.norm()) < 1e-4
    if w_l1 and not w_ssim:
        assert torch.all(leaf.grad[3, :7] == 0)


def test_photometric_takes_the_fused_kernel_and_matches_the_torch_path():
    a, b = natural_pair(64, 48)
    leaf = a.float().requires_grad_(True)
    l1, dssim = losses.photometric(leaf, b.float(), 0.2)
    (0.8 * l1 + 0.2 * dssim).backward()
    assert "L1Ssim" in type(l1.grad_fn).__name__
    ref_l1, ref_value, ref_grad = l1_ssim_oracle(a, b, 0.8, 0.2)
    assert float(dssim.detach()) == pytest.approx(1.0 - float(ref_value), abs=1e-5)
    assert float(l1.detach()) == pytest.approx(float(ref_l1), rel=1e-6)
    assert float((leaf.grad.double() - ref_grad).norm() / ref_grad.norm()) < 1e-4
    torch64 = losses.photometric(a, b, 0.2)  # float64: the torch path
    assert float(torch64[0]) == pytest.approx(float(ref_l1)) and float(torch64[1]) == pytest.approx(
        1 - float(ref_value)
    )
