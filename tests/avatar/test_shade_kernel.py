"""The distant-light shading kernel (stg_node.splat.shade_ops) against the avatar's torch shading
(stg_node.avatar.shading.Shading, its reference) in float64: values and the gradients of the
albedo, the normals, the occlusion strength and every light parameter; rows facing away; the
baked mode; no occlusion."""

from __future__ import annotations

import copy

import pytest
import torch

from stg_node.avatar import kernels
from stg_node.avatar.shading import LightSpec, Shading
from stg_node.splat import shade_ops

pytestmark = pytest.mark.usefixtures("cpu_kernels")  # skips where the kernels cannot build


def _shading(count: int, occlusion: bool, seed: int = 0) -> Shading:
    torch.manual_seed(seed)
    shading = Shading("distant", count, occlusion=occlusion)
    with torch.no_grad():  # a learned light, not the uniform start
        shading.light.ambient.copy_(torch.randn(3) * 0.5)
        shading.light.colors.copy_(torch.randn(count, 3))
        shading.light.directions.copy_(torch.randn(count, 3))
        if occlusion:
            shading.occlusion.strength_logit.fill_(0.4)
    return shading


def _run(shading, albedo, normals, visible, away, g, light=None, root=None):
    leaves = [albedo.clone().requires_grad_(True), normals.clone().requires_grad_(True)]
    out = shading(leaves[0], leaves[1], light, root, visible, away)
    params = [p for p in shading.parameters() if p.requires_grad]
    grads = torch.autograd.grad((out * g).sum(), [*leaves, *params])
    return out.detach(), grads


@pytest.mark.parametrize(
    "count, occlusion, with_away, mode",
    [
        (2, True, False, "learned"),
        (2, True, True, "learned"),
        (1, False, False, "learned"),
        (4, True, False, "baked"),
    ],
)
def test_shading_kernel_matches_torch_in_float64(count, occlusion, with_away, mode):
    gen = torch.Generator().manual_seed(count)
    m = 333
    albedo = torch.rand(m, 3, generator=gen, dtype=torch.float64)
    normals = torch.nn.functional.normalize(torch.randn(m, 3, generator=gen, dtype=torch.float64), dim=1)
    visible = torch.rand(m, generator=gen, dtype=torch.float64) if occlusion else None
    away = torch.rand(m, generator=gen) < 0.3 if with_away else None
    g = torch.randn(m, 3, generator=gen, dtype=torch.float64)
    light = None if mode == "learned" else LightSpec(mode="baked")
    root = torch.linalg.matrix_exp(torch.tensor([[0.0, -0.4, 0.2], [0.4, 0.0, -0.1], [-0.2, 0.1, 0.0]]))
    shading = _shading(count, occlusion)
    shading64 = copy.deepcopy(shading).double()
    want, want_grads = _run(shading64, albedo, normals, visible, away, g, light, root.double())
    assert not shading._fused(albedo, normals, visible)  # float64: the torch path, the reference
    f32 = [None if t is None else t.float() for t in (albedo, normals, visible)]
    assert shading._fused(*f32)
    out, grads = _run(shading, *f32[:2], f32[2], away, g.float(), light, root)
    torch.testing.assert_close(out.double(), want, atol=1e-5, rtol=1e-5)
    assert len(grads) == len(want_grads)
    for got, ref in zip(grads, want_grads, strict=True):
        torch.testing.assert_close(got.double(), ref, atol=2e-5 * max(float(ref.abs().max()), 1.0), rtol=1e-4)
    with kernels.reference():  # and the float32 torch path agrees with the kernel
        ref32, _ = _run(shading, *f32[:2], f32[2], away, g.float(), light, root)
    torch.testing.assert_close(out, ref32, atol=1e-6, rtol=1e-5)


def test_rows_facing_away_teach_the_light_nothing():
    shading = _shading(2, True)
    m = 50
    albedo, normals = torch.rand(m, 3), torch.nn.functional.normalize(torch.randn(m, 3), dim=1)
    visible = torch.rand(m)
    away = torch.ones(m, dtype=torch.bool)
    out, grads = _run(shading, albedo, normals, visible, away, torch.ones(m, 3))
    assert torch.equal(grads[1], torch.zeros_like(grads[1]))  # normals
    params = [p for p in shading.parameters() if p.requires_grad]
    strength = shading.occlusion.strength_logit
    for p, g in zip(params, grads[2:], strict=True):
        if p is strength:  # the albedo's occlusion factor still learns
            assert float(g.abs().sum()) > 0
        else:
            assert torch.equal(g, torch.zeros_like(g))
    assert float(grads[0].abs().sum()) > 0


def test_bad_inputs_are_refused():
    a, c, d = torch.ones(3), torch.ones(2, 3), torch.ones(2, 3)
    rgb = torch.ones(4, 3)
    with pytest.raises(ValueError, match="albedo"):
        shade_ops.shade(torch.ones(4, 2), rgb, None, None, a, c, d)
    with pytest.raises(ValueError, match="strength"):
        shade_ops.shade(rgb, rgb, torch.ones(4), None, a, c, d)
    with pytest.raises(ValueError, match="away"):
        shade_ops.shade(rgb, rgb, None, None, a, c, d, away=torch.ones(4))
    with pytest.raises(ValueError, match="lights"):
        shade_ops.shade(rgb, rgb, None, None, a, torch.ones(9, 3), torch.ones(9, 3))
