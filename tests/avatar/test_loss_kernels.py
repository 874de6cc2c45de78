"""The training step's loss kernels against their torch references in float64: the flow term's
C++ kernel (losses.flow_loss on float32 CPU tensors) and mean_square, values and gradients."""

from __future__ import annotations

import pytest
import torch

from stg_node.avatar import losses as L

pytestmark = pytest.mark.usefixtures("cpu_kernels")  # skips where the kernels cannot build


def flow_case(h=37, w=29, seed=0):
    """Rendered flow and alpha as a step has them (alpha in [0, 1], some pixels exactly at the 0.5
    threshold, some transparent), an observed flow that holds NaN where it is invalid."""
    gen = torch.Generator().manual_seed(seed)
    alpha = torch.rand(h, w, 1, generator=gen, dtype=torch.float64)
    alpha[0, :5] = 0.5
    alpha[1, :5] = 0.0
    rendered = alpha * 3.0 * torch.randn(h, w, 2, generator=gen, dtype=torch.float64)
    flow = 3.0 * torch.randn(h, w, 2, generator=gen, dtype=torch.float64)
    valid = torch.rand(h, w, generator=gen) > 0.25
    flow[~valid] = float("nan")
    return rendered, alpha, flow, valid


def value_and_grads(fn, rendered, alpha, flow, valid, dtype):
    r = rendered.detach().to(dtype).requires_grad_(True)
    a = alpha.detach().to(dtype).requires_grad_(True)
    loss = fn(r, a, flow.to(dtype), valid)
    (2.5 * loss).backward()
    return loss.detach().double(), r.grad.double(), a.grad.double()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_flow_kernel_matches_float64_autograd(seed):
    case = flow_case(seed=seed)
    value, g_r, g_a = value_and_grads(L.flow_loss, *case, torch.float32)
    ref, ref_r, ref_a = value_and_grads(L.flow_loss_torch, *case, torch.float64)
    assert value.item() == pytest.approx(ref.item(), rel=1e-5)
    torch.testing.assert_close(g_r, ref_r, rtol=1e-4, atol=1e-6 * ref_r.abs().max().item())
    torch.testing.assert_close(g_a, ref_a, rtol=1e-4, atol=1e-6 * ref_a.abs().max().item())
    assert torch.isfinite(g_r).all() and torch.isfinite(g_a).all()
    unused = ~(case[3] & (case[1][..., 0] > 0.5))
    assert torch.all(g_r[unused] == 0) and torch.all(g_a[unused] == 0)


def test_flow_kernel_takes_float32_cpu_and_a_non_contiguous_flow():
    rendered, alpha, flow, valid = flow_case()
    image = torch.cat([torch.rand(*rendered.shape[:2], 3, dtype=torch.float64), rendered], dim=-1).float()
    image.requires_grad_(True)
    _, motion = image.split([3, 2], dim=-1)  # a view into the rendered image, as in a step
    loss = L.flow_loss(motion, alpha.float(), flow.float(), valid)
    assert "FlowLoss" in type(loss.grad_fn).__name__
    loss.backward()
    ref, ref_r, _ = value_and_grads(L.flow_loss_torch, rendered, alpha, flow, valid, torch.float64)
    assert loss.item() == pytest.approx(ref.item(), rel=1e-5)
    torch.testing.assert_close(image.grad[..., 3:].double() * 2.5, ref_r, rtol=1e-4, atol=1e-6)
    assert torch.all(image.grad[..., :3] == 0)


def test_flow_kernel_without_a_used_pixel_is_zero_without_gradient():
    rendered, alpha, flow, valid = flow_case()
    r = rendered.float().requires_grad_(True)
    loss = L.flow_loss(r, alpha.float(), flow.float(), torch.zeros_like(valid))
    assert loss.item() == 0.0
    (loss + r.sum() * 0.0).backward()
    assert torch.all(r.grad == 0)


def test_mean_square_matches_pow_mean():
    gen = torch.Generator().manual_seed(4)
    x = torch.randn(300, 24, generator=gen, dtype=torch.float64, requires_grad=True)
    y = x.detach().clone().requires_grad_(True)
    (3.0 * L.mean_square(x)).backward()
    (3.0 * y.pow(2).mean()).backward()
    torch.testing.assert_close(x.grad, y.grad)
    assert L.mean_square(x).item() == pytest.approx(y.pow(2).mean().item())
    assert L.mean_square(torch.zeros(0, 24)).isnan()  # as the mean of nothing is


def test_mean_abs_difference_matches_autograd_bit_for_bit():
    """The mask term's one-node L1 against (a - b).abs().mean() under autograd: the same value and
    gradient, exactly (sign times grad / n in both), ties (a == b) included."""
    gen = torch.Generator().manual_seed(4)
    a = torch.rand(40, 30, generator=gen, dtype=torch.float64)
    b = (torch.rand(40, 30, generator=gen) > 0.5).double()
    a[:5] = b[:5]  # exact ties: zero gradient on both paths
    x, y = a.clone().requires_grad_(True), a.clone().requires_grad_(True)
    got, want = L.mean_abs_difference(x, b), (y - b).abs().mean()
    assert got.grad_fn.name() != want.grad_fn.name()
    assert torch.equal(got, want)
    (2.5 * got).backward()
    (2.5 * want).backward()
    assert torch.equal(x.grad, y.grad) and x.grad[:5].abs().max() == 0
