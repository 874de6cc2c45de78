"""The distant lights' irradiance with its written-out backward against torch autograd on the
reference composition (stg_node.avatar.light_ops), float64."""

import pytest
import torch

from stg_node.avatar import kernels
from stg_node.avatar.light_ops import distant_irradiance, distant_irradiance_reference
from stg_node.avatar.shading import DistantLights


def _inputs(m: int = 300, k: int = 3, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    normals = torch.nn.functional.normalize(torch.randn(m, 3, generator=gen, dtype=torch.float64), dim=1)
    ambient = torch.rand(3, generator=gen, dtype=torch.float64) + 0.2
    colors = torch.rand(k, 3, generator=gen, dtype=torch.float64)
    directions = torch.nn.functional.normalize(torch.randn(k, 3, generator=gen, dtype=torch.float64), dim=1)
    mean = ambient + colors.sum(0) / 4.0
    return normals, ambient, colors, directions, mean


@pytest.mark.parametrize("with_away", [False, True])
def test_values_and_gradients_match_autograd(with_away):
    inputs = _inputs()
    away = torch.rand(300, generator=torch.Generator().manual_seed(8)) < 0.3 if with_away else None
    weights = torch.randn(300, 3, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
    a = [t.clone().requires_grad_(True) for t in inputs]
    b = [t.clone().requires_grad_(True) for t in inputs]
    out_a, out_b = distant_irradiance(*a, away=away), distant_irradiance_reference(*b, away=away)
    assert out_a.grad_fn.name() != out_b.grad_fn.name()  # two implementations compared
    torch.testing.assert_close(out_a, out_b, rtol=1e-14, atol=1e-15)
    (out_a * weights).sum().backward()
    (out_b * weights).sum().backward()
    for x, y in zip(a, b, strict=True):
        torch.testing.assert_close(x.grad, y.grad, rtol=1e-12, atol=1e-13)
    if with_away:  # the held rows pass nothing to their normals
        assert a[0].grad[away].abs().max() == 0 and a[0].grad[~away].abs().max() > 0


def test_gradcheck_with_some_inputs_frozen():
    normals, ambient, colors, directions, mean = _inputs(40, 2, seed=1)
    args = (normals.requires_grad_(), ambient, colors.requires_grad_(), directions.requires_grad_(), mean)
    assert torch.autograd.gradcheck(distant_irradiance, args)


def test_the_light_module_through_both_paths():
    """DistantLights.irradiance (softplus, normalised directions, mean) agrees with the reference
    mode end to end, float32 as training runs it."""
    light = DistantLights(2)
    with torch.no_grad():
        light.colors.add_(torch.tensor([[2.0, 1.0, 0.5], [0.3, 0.2, 2.5]]))
    gen = torch.Generator().manual_seed(3)
    normals = torch.nn.functional.normalize(torch.randn(500, 3, generator=gen), dim=1)
    away = torch.rand(500, generator=gen) < 0.25
    grads = []
    for reference in (False, True):
        light.zero_grad()
        n = normals.clone().requires_grad_(True)
        if reference:
            with kernels.reference():
                out = light.irradiance(n, away)
        else:
            out = light.irradiance(n, away)
        (out * torch.linspace(-1, 1, 1500).reshape(500, 3)).sum().backward()
        grads.append((out.detach(), n.grad, *(p.grad.clone() for p in light.parameters())))
    for x, y in zip(*grads, strict=True):
        torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-5)  # float32 sums over 500 rows
