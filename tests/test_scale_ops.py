"""The capped scales and the largest axis with their written-out backward against torch autograd
(stg_node.avatar.scale_ops; the reference is gaussians.cap_scale_ratio and torch.max), float64."""

import pytest
import torch

from stg_node.avatar import kernels
from stg_node.avatar.gaussians import cap_scale_ratio
from stg_node.avatar.scale_ops import capped_scales, largest_scale


def _log_scales(n: int = 400, seed: int = 0) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(n, 3, generator=gen, dtype=torch.float64) * 1.5 - 4.0
    x[:40] = x[:40, :1]  # isotropic rows (as initialised): three-way ties of the largest axis
    x[40:80, 1] = x[40:80, 0]  # two-way ties
    x[80:120, 2] = x[80:120, 1]
    return x


def _compare(fast, reference, x: torch.Tensor, weights: torch.Tensor):
    a = x.clone().requires_grad_(True)
    b = x.clone().requires_grad_(True)
    out_a, out_b = fast(a), reference(b)
    torch.testing.assert_close(out_a, out_b, rtol=1e-14, atol=0)
    (out_a * weights).sum().backward()
    (out_b * weights).sum().backward()
    torch.testing.assert_close(a.grad, b.grad, rtol=1e-12, atol=1e-300)


@pytest.mark.parametrize("ratio", [1.0, 3.0, 10.0])
def test_capped_scales_match_torch_autograd(ratio):
    x = _log_scales()
    weights = torch.randn(x.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    with torch.no_grad():
        raised = cap_scale_ratio(x.exp(), ratio) != x.exp()
    assert raised.any() or ratio == 1.0  # the cap is exercised
    _compare(lambda t: capped_scales(t, ratio), lambda t: cap_scale_ratio(t.exp(), ratio), x, weights)


def test_capped_scales_tie_with_the_floor():
    """An axis exactly at the floor: torch.maximum splits the gradient half and half."""
    x = torch.log(torch.tensor([[1.0, 0.25, 0.5], [2.0, 2.0, 0.5]], dtype=torch.float64))
    weights = torch.tensor([[1.0, 2.0, 3.0], [0.5, -1.0, 4.0]], dtype=torch.float64)
    _compare(lambda t: capped_scales(t, 4.0), lambda t: cap_scale_ratio(t.exp(), 4.0), x, weights)


def test_largest_scale_matches_torch_max():
    x = _log_scales(seed=2)
    weights = torch.randn(x.shape[0], generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    _compare(largest_scale, lambda t: t.exp().max(dim=1).values, x, weights)


def test_gradcheck():
    # random rows: no ties, where the maximum is smooth
    gen = torch.Generator().manual_seed(5)
    x = (torch.randn(30, 3, dtype=torch.float64, generator=gen) - 2).requires_grad_()
    assert torch.autograd.gradcheck(lambda t: capped_scales(t, 2.0), (x,))
    assert torch.autograd.gradcheck(largest_scale, (x,))


def test_reference_mode_runs_the_torch_composition():
    x = _log_scales(50).requires_grad_(True)
    with kernels.reference():
        out = capped_scales(x, 10.0)
    assert out.grad_fn.name() == "MaximumBackward0"
    assert capped_scales(x, 10.0).grad_fn.name() != "MaximumBackward0"


def test_no_cap_is_the_plain_exponential():
    x = _log_scales(50)
    torch.testing.assert_close(capped_scales(x, 0.0), x.exp(), rtol=0, atol=0)


def test_float32_forward_is_bit_identical():
    x = _log_scales(2000, seed=6).float()
    assert torch.equal(capped_scales(x, 10.0), cap_scale_ratio(x.exp(), 10.0))
    assert torch.equal(largest_scale(x), x.exp().max(dim=1).values)


def test_no_gradient_in_gives_none_out():
    """A consumer passing no gradient to the scales leaves the log column without one, as torch's
    own nodes do (a zero tensor would differ from the reference path)."""

    class Blocks(torch.autograd.Function):
        @staticmethod
        def forward(ctx, x):
            return x.sum()

        @staticmethod
        def backward(ctx, grad):
            return None

    x = _log_scales(20).requires_grad_(True)
    y = torch.ones((), requires_grad=True)
    (Blocks.apply(capped_scales(x, 10.0)) + Blocks.apply(largest_scale(x)) + y).backward()
    assert x.grad is None


@pytest.mark.usefixtures("cpu_kernels")
@pytest.mark.parametrize("ratio", [1.0, 3.0, 10.0])
def test_the_kernel_equals_the_elementwise_composition_bit_for_bit(ratio):
    """csrc/scale_cap.cpp against the torch composition it replaces (float32, ties and floor ties
    included): the same outputs and gradients to the bit."""
    from stg_node.avatar.scale_ops import _CappedScales, _LargestScale

    x = _log_scales(3000, seed=7).float()
    x[200:240] = torch.log(torch.tensor([1.0, 1.0 / ratio, 0.5]))  # an axis exactly at the floor
    weights = torch.randn(x.shape, generator=torch.Generator().manual_seed(8))
    for fn, w in (
        (lambda t, k: _CappedScales.apply(t, ratio, k), weights),
        (_LargestScale.apply, weights[:, 0]),
    ):
        results = []
        for use_kernel in (True, False):
            t = x.clone().requires_grad_(True)
            out = fn(t, use_kernel)
            (out * w).sum().backward()
            results.append((out.detach(), t.grad))
        assert torch.equal(results[0][0], results[1][0])
        assert torch.equal(results[0][1], results[1][1])


@pytest.mark.usefixtures("cpu_kernels")
def test_the_kernel_propagates_nan_as_torch_maximum():
    from stg_node.avatar.scale_ops import _CappedScales, _LargestScale

    x = torch.tensor([[0.0, float("nan"), -1.0], [-1.0, -2.0, -3.0]])
    for use_kernel in (True, False):
        capped = _CappedScales.apply(x, 3.0, use_kernel)
        assert capped[0].isnan().all() and not capped[1].isnan().any()
        assert _LargestScale.apply(x, use_kernel)[0].isnan()
