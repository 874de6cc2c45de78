"""Rigid part: the avatar's Skeleton and Gaussian skinning against the body model's own forward pass."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from stg_node.avatar.rigid import Skeleton, blend_weights, skin
from stg_node.body import canonical_transforms, lbs, load_body_model
from stg_node.body.canonical import big_pose_output


@pytest.fixture(scope="module")
def body():
    return load_body_model(dtype=torch.float64)


def _random_pose(seed: int):
    rng = np.random.default_rng(seed)
    poses = torch.tensor(rng.normal(0, 0.3, (1, 24, 3)))
    Rh = torch.tensor(rng.normal(0, 1.0, (1, 3)))
    Th = torch.tensor(rng.normal(0, 1.0, (1, 3)))
    betas = torch.tensor(rng.normal(0, 0.5, (1, 10)))
    return poses, Rh, Th, betas


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("grad", [True, False], ids=["torch", "numpy-no-grad"])
def test_skeleton_bones_equal_body_canonical_transforms(body, seed, grad):
    poses, Rh, Th, betas = _random_pose(seed)
    skeleton = Skeleton.from_body(body, betas).double()
    truth = canonical_transforms(body, betas, poses.reshape(1, 72), Rh, Th)
    bones = skeleton.bones(poses.requires_grad_(grad), Rh, Th)
    assert bones.transforms.dtype == torch.float64 and bones.transforms.requires_grad == grad
    assert torch.allclose(bones.transforms.detach(), truth, atol=1e-6)  # the Skeleton stores float32


@pytest.mark.parametrize("seed", [0, 5])
def test_bones_without_gradient_match_the_differentiable_path_quaternions_included(body, seed):
    """The no-gradient kinematics (numpy) against the torch path: transforms and the one-hemisphere
    quaternions, in float32 as a renderer uses them, at small and large joint angles."""
    poses, Rh, Th, betas = _random_pose(seed)
    skeleton = Skeleton.from_body(body, betas)
    for scale in (0.0, 1.0, 6.0):
        p = (poses * scale).float()
        with_grad = skeleton.bones(p.clone().requires_grad_(True), Rh.float(), Th.float())
        with torch.no_grad():
            plain = skeleton.bones(p, Rh.float(), Th.float())
        assert plain.transforms.dtype == torch.float32
        torch.testing.assert_close(plain.transforms, with_grad.transforms.detach(), atol=2e-6, rtol=0)
        torch.testing.assert_close(plain.quats, with_grad.quats.detach(), atol=2e-6, rtol=0)


@pytest.mark.parametrize("seed", [3, 4])
def test_skinning_the_canonical_mesh_reproduces_the_posed_body(body, seed):
    """Skinning the big-pose mesh lands on the body's posed vertices (the body skins from its rest
    pose instead: an independent path). Exactly so for vertices bound to one bone; elsewhere the
    two blends differ by the blend-of-blends error, which stays small for a human pose."""
    poses, Rh, Th, betas = _random_pose(seed)
    canonical = big_pose_output(body, betas).vertices[0]
    skeleton = Skeleton.from_body(body, betas).double()
    skinned = skin(canonical, body.weights, skeleton.bones(poses, Rh, Th))
    truth = body(betas=betas, poses=poses.reshape(1, 72), Rh=Rh, Th=Th, pose_blendshapes=False).vertices[0]
    rigid = body.weights.max(dim=1).values > 1.0 - 1e-9
    assert int(rigid.sum()) > 1000
    assert torch.allclose(skinned.means[rigid], truth[rigid], atol=1e-6)  # the Skeleton stores float32
    assert float((skinned.means - truth).norm(dim=1).max()) < 0.05  # metres


@pytest.mark.parametrize("seed", [5, 6])
def test_blended_rotation_is_the_bone_rotation_when_bound_to_one_bone_and_near_the_polar_factor(body, seed):
    from stg_node.body import lbs

    poses, Rh, Th, betas = _random_pose(seed)
    skeleton = Skeleton.from_body(body, betas).double()
    bones = skeleton.bones(poses, Rh, Th)
    skinned = skin(big_pose_output(body, betas).vertices[0], body.weights, bones)
    q = skinned.quats
    assert torch.allclose(q.norm(dim=1), torch.ones(q.shape[0], dtype=q.dtype), atol=1e-9)
    R = lbs.quaternion_to_matrix(q)
    rigid = body.weights.max(dim=1).values > 1.0 - 1e-9
    linear = skinned.blended[:, :3, :3]
    assert torch.allclose(R[rigid], linear[rigid], atol=1e-6)
    # Elsewhere: within a few degrees of the nearest rotation to the blended matrix.
    polar = lbs.closest_rotation(linear, iterations=8)
    cos = ((torch.einsum("nij,nij->n", R, polar) - 1) / 2).clamp(-1, 1)
    assert float(torch.rad2deg(torch.acos(cos)).max()) < 10.0


def test_learned_weight_correction_is_identity_at_zero_and_rows_sum_to_one():
    w = torch.softmax(torch.randn(50, 24), dim=1)
    assert blend_weights(w, None) is w
    corrected = blend_weights(w, torch.zeros(50, 24))
    assert torch.allclose(corrected, w, atol=3e-3)
    moved = blend_weights(w, torch.randn(50, 24))
    assert torch.allclose(moved.sum(1), torch.ones(50))


def test_skeleton_refuses_wrong_shapes():
    with pytest.raises(ValueError, match="rest_joints"):
        Skeleton(torch.zeros(23, 3), torch.zeros(24, dtype=torch.long), torch.eye(4).expand(24, 4, 4))


def test_matrix_to_quaternion_gradient_is_finite_at_half_turns():
    """A blended rotation of exactly 180 degrees (or the identity) must not send NaN back through the
    unused quaternion candidates (the trainer skipped steps before this was fixed)."""
    from stg_node.body import lbs

    angles = torch.tensor([[np.pi, 0, 0], [0, np.pi, 0], [0, 0, 0.0], [0, 0, np.pi]], requires_grad=True)
    q = lbs.matrix_to_quaternion(lbs.axis_angle_to_matrix(angles))
    q.sum().backward()
    assert torch.isfinite(angles.grad).all()


@pytest.mark.parametrize("grad", [True, False], ids=["torch", "numpy-no-grad"])
def test_bone_quaternions_are_the_bone_rotations_each_in_its_parents_hemisphere(body, grad):
    poses, Rh, Th, betas = _random_pose(7)
    skeleton = Skeleton.from_body(body, betas)
    angles = (poses * 6.0).float().requires_grad_(grad)
    bones = skeleton.bones(angles, Rh.float(), Th.float())
    quats = bones.quats.detach()[0]
    rotations = bones.transforms.detach()[0, :, :3, :3]
    torch.testing.assert_close(lbs.quaternion_to_matrix(quats), rotations, atol=1e-5, rtol=0)
    torch.testing.assert_close(quats.norm(dim=1), torch.ones(24), atol=1e-6, rtol=0)
    parents = skeleton.parent_list
    dots = torch.stack([(quats[j] * quats[parents[j]]).sum() for j in range(1, 24)])
    assert (dots >= 0).all()
    if grad:  # the signs are constants: the gradient reaches the pose through every joint
        (g,) = torch.autograd.grad(bones.quats.sum() + bones.transforms.sum(), angles)
        assert torch.isfinite(g).all() and (g[0].abs().sum(dim=1) > 0).all()


def _bones_about_z(angles_deg):
    """24 bones, bone b turned by angles_deg[b] (0 for the rest) about z, no translation."""
    from stg_node.avatar.rigid import PosedBones
    from stg_node.body import lbs

    angles = torch.zeros(24, dtype=torch.float64)
    angles[: len(angles_deg)] = torch.tensor(angles_deg, dtype=torch.float64)
    axis_angle = torch.zeros(24, 3, dtype=torch.float64)
    axis_angle[:, 2] = torch.deg2rad(angles)
    transforms = torch.eye(4, dtype=torch.float64).repeat(24, 1, 1)
    transforms[:, :3, :3] = lbs.axis_angle_to_matrix(axis_angle)
    return PosedBones.from_transforms(transforms[None], list(range(-1, 23)))


@pytest.mark.parametrize("angle", [0.0, 20.0, 90.0, 150.0])
def test_joint_shrink_is_the_squeeze_of_the_blended_matrix(angle):
    """Two bones turned ``angle`` apart about z, the point weighted half and half: the blended
    matrix's singular values in the plane of the bend (numpy's SVD, an independent path) are the
    factor; a point on one bone is not shrunk."""
    from stg_node.avatar.rigid import blend, joint_shrink

    bones = _bones_about_z([0.0, angle])
    weights = torch.zeros(2, 24, dtype=torch.float64)
    weights[0, :2] = 0.5
    weights[1, 1] = 1.0
    factor = joint_shrink(weights, bones, floor=0.0)
    matrix = blend(weights, bones)[0, :3, :3].numpy()
    singular = np.linalg.svd(matrix, compute_uv=False)
    assert factor[0].item() == pytest.approx(np.cos(np.radians(angle) / 2), abs=1e-9)
    assert sorted(singular)[:2] == pytest.approx([factor[0].item()] * 2, abs=1e-9)
    assert factor[1].item() == pytest.approx(1.0, abs=1e-12)


def test_joint_shrink_is_floored_and_posing_applies_it():
    """Opposite bones squeeze to nothing: the floor holds. A model posed with the shrink on renders
    the Gaussians of a bent joint smaller by the factor, and those on one bone unchanged."""
    from stg_node.avatar.rigid import JOINT_SHRINK_FLOOR, joint_shrink

    bones = _bones_about_z([0.0, 180.0])
    weights = torch.zeros(1, 24, dtype=torch.float64)
    weights[0, :2] = 0.5
    assert joint_shrink(weights, bones).item() == pytest.approx(JOINT_SHRINK_FLOOR)


@pytest.mark.parametrize("seed", [0, 7])
def test_hand_written_kinematics_backward_matches_torch_autograd_in_float64(body, seed):
    """Skeleton.bones with a gradient (stg_node.avatar.kinematics: numpy forward, the chain rule by
    hand) against the torch path under kernels.reference(), in float64: the transforms and
    quaternions, and the gradients of the pose, root rotation and translation of a loss over both,
    two frames at once, at the rest pose (the small-angle series), human and large joint angles.
    The quaternions' gradient treats every change of a bone rotation as a rotation's, exact for
    the float32-stored big-pose inverse to its orthogonality (~1e-7)."""
    from stg_node.avatar import kernels

    poses, Rh, Th, betas = _random_pose(seed)
    skeleton = Skeleton.from_body(body, betas).double()
    gen = torch.Generator().manual_seed(seed)
    g_transforms = torch.randn(2, 24, 4, 4, generator=gen, dtype=torch.float64)
    g_quats = torch.randn(2, 24, 4, generator=gen, dtype=torch.float64)
    for scale in (0.0, 1.0, 6.0):
        p = torch.cat([poses * scale, poses.flip(1) * scale]).reshape(2, 72)  # (B, 72) as the trainer's
        rh, th = torch.cat([Rh, -Rh]), torch.cat([Th, 2 * Th])
        results = []
        for reference in (True, False):
            ins = [t.clone().requires_grad_(True) for t in (p, rh, th)]
            if reference:
                with kernels.reference():
                    bones = skeleton.bones(*ins)
            else:
                bones = skeleton.bones(*ins)
            loss = (bones.transforms * g_transforms).sum() + (bones.quats * g_quats).sum()
            results.append((bones, torch.autograd.grad(loss, ins)))
        (want, want_grads), (got, got_grads) = results
        torch.testing.assert_close(got.transforms, want.transforms, atol=1e-12, rtol=0)
        torch.testing.assert_close(got.quats, want.quats, atol=1e-12, rtol=0)
        for name, a, b in zip(("poses", "Rh", "Th"), got_grads, want_grads, strict=True):
            assert a.shape == b.shape and a.dtype == torch.float64
            torch.testing.assert_close(a, b, atol=1e-6 * float(b.abs().max()), rtol=0, msg=name)


@pytest.mark.parametrize("scale", [0.0, 1e-5, 1.0, 3.0])
def test_pose_code_rotations_match_torch_autograd_in_float64(scale):
    """kinematics.rotation_matrices (the colour MLP's pose code with a gradient: numpy Rodrigues,
    the backward by hand) against lbs.axis_angle_to_matrix under autograd, float64, at the rest
    pose and tiny angles (the small-angle series), human and large angles."""
    from stg_node.avatar import kinematics

    gen = torch.Generator().manual_seed(11)
    p = torch.randn(23, 3, generator=gen, dtype=torch.float64) * scale
    weights = torch.randn(23, 3, 3, generator=gen, dtype=torch.float64)
    a, b = p.clone().requires_grad_(True), p.clone().requires_grad_(True)
    got, want = kinematics.rotation_matrices(a), lbs.axis_angle_to_matrix(b)
    assert got.grad_fn.name() != want.grad_fn.name()
    torch.testing.assert_close(got, want, atol=1e-14, rtol=0)
    (got * weights).sum().backward()
    (want * weights).sum().backward()
    torch.testing.assert_close(a.grad, b.grad, atol=1e-12, rtol=1e-10)
