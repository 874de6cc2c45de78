"""The skeleton kinematics' C++ kernel (csrc/kinematics.cpp) against its numpy reference
(stg_node.avatar.kinematics under numpy_reference()), in float64: the bones' transforms and
hemisphere-signed quaternions, the colour MLP's pose-code rotations, and the gradients of both."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from stg_node.avatar import kinematics
from stg_node.avatar.rigid import Skeleton
from stg_node.body import load_body_model

pytestmark = pytest.mark.usefixtures("cpu_kernels")  # skips where the kernels cannot build


@pytest.fixture(scope="module")
def skeleton():
    rng = np.random.default_rng(5)
    betas = torch.tensor(rng.normal(0, 0.5, (1, 10)))
    return Skeleton.from_body(load_body_model(dtype=torch.float64), betas).double()


def _both(fn):
    """fn() under the C++ kernel, then under the numpy reference."""
    assert kinematics._kernel_ops() is not None
    got = fn()
    with kinematics.numpy_reference():
        want = fn()
    return got, want


@pytest.mark.parametrize("scale", [0.0, 1e-5, 1.0, 6.0])  # rest pose, the small-angle series, human, large
def test_bones_and_their_gradients_match_numpy_in_float64(skeleton, scale):
    gen = torch.Generator().manual_seed(int(scale * 10) + 1)
    p = torch.randn(2, 72, generator=gen, dtype=torch.float64) * 0.5 * scale
    rh = torch.randn(2, 3, generator=gen, dtype=torch.float64) * max(scale, 1e-5)
    th = torch.randn(2, 3, generator=gen, dtype=torch.float64)
    g_transforms = torch.randn(2, 24, 4, 4, generator=gen, dtype=torch.float64)
    g_quats = torch.randn(2, 24, 4, generator=gen, dtype=torch.float64)

    def run():
        ins = [t.clone().requires_grad_(True) for t in (p, rh, th)]
        transforms, quats = kinematics.bones(skeleton, *ins)
        loss = (transforms * g_transforms).sum() + (quats * g_quats).sum()
        return transforms, quats, torch.autograd.grad(loss, ins)

    (t1, q1, g1), (t2, q2, g2) = _both(run)
    assert t1.grad_fn is not None and t1.dtype == torch.float64
    torch.testing.assert_close(t1, t2, atol=1e-12, rtol=0)
    torch.testing.assert_close(q1, q2, atol=1e-12, rtol=0)
    for name, a, b in zip(("poses", "Rh", "Th"), g1, g2, strict=True):
        torch.testing.assert_close(a, b, atol=1e-10 * max(float(b.abs().max()), 1.0), rtol=0, msg=name)


def test_only_the_quaternions_or_only_the_transforms_take_a_gradient(skeleton):
    """A loss over one output: the other's gradient arrives as None (no zeros made up for it)."""
    gen = torch.Generator().manual_seed(3)
    p = torch.randn(1, 72, generator=gen, dtype=torch.float64) * 0.4
    rh, th = torch.randn(1, 3, generator=gen, dtype=torch.float64), torch.zeros(1, 3, dtype=torch.float64)
    for which in (0, 1):

        def run(which=which):
            ins = [t.clone().requires_grad_(True) for t in (p, rh, th)]
            out = kinematics.bones(skeleton, *ins)[which]
            return torch.autograd.grad(out.square().sum(), ins)

        got, want = _both(run)
        for a, b in zip(got, want, strict=True):
            torch.testing.assert_close(a, b, atol=1e-10 * max(float(b.abs().max()), 1.0), rtol=0)


@pytest.mark.parametrize("scale", [0.0, 1e-5, 1.0, 3.0])
def test_pose_code_rotations_and_their_gradient_match_numpy_in_float64(scale):
    gen = torch.Generator().manual_seed(7)
    p = torch.randn(23, 3, generator=gen, dtype=torch.float64) * scale
    weights = torch.randn(23, 3, 3, generator=gen, dtype=torch.float64)

    def run():
        a = p.clone().requires_grad_(True)
        rotations = kinematics.rotation_matrices(a)
        return rotations, torch.autograd.grad((rotations * weights).sum(), a)[0]

    (r1, g1), (r2, g2) = _both(run)
    torch.testing.assert_close(r1, r2, atol=1e-14, rtol=0)
    torch.testing.assert_close(g1, g2, atol=1e-12, rtol=0)


def test_the_kernel_refuses_a_parent_after_its_child():
    from stg_node.splat.build import load_kernels

    f64 = torch.float64
    parents = torch.tensor([-1, 2, 0])  # joint 1's parent comes later
    with pytest.raises(RuntimeError, match="earlier joint"):
        load_kernels().ops.kin_bones_fwd(
            torch.zeros(1, 3, 3, dtype=f64), torch.zeros(1, 3, dtype=f64), torch.zeros(1, 3, dtype=f64),
            torch.zeros(3, 3, dtype=f64), parents, torch.eye(4, dtype=f64).repeat(3, 1, 1),
        )  # fmt: skip
