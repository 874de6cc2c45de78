"""LBS math against independent truth: scipy's rotations, exact inverses, rigid special cases."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from smpl_fixtures import random_smpl_arrays, write_smpl_npz

from stg_node.body import (
    BIG_POSE,
    axis_angle_to_matrix,
    big_pose_output,
    canonical_transforms,
    load_body_model,
    matrix_to_axis_angle,
    matrix_to_quaternion,
    nearest_vertex_weights,
    quaternion_to_matrix,
    skin_points,
    skin_rotations,
)


def test_rotations_match_scipy():
    rng = np.random.default_rng(0)
    rotvecs = rng.normal(0, 1.2, (500, 3))
    rotvecs[:5] = [[0, 0, 0], [1e-9, 0, 0], [np.pi, 0, 0], [0, 0, -np.pi + 1e-6], [0, 3.0, 0]]
    ref = Rotation.from_rotvec(rotvecs)
    mats = axis_angle_to_matrix(torch.as_tensor(rotvecs))
    assert np.allclose(mats.numpy(), ref.as_matrix(), atol=1e-12)
    quats = matrix_to_quaternion(mats).numpy()
    ref_q = ref.as_quat()[:, [3, 0, 1, 2]]  # scipy is xyzw
    ref_q *= np.sign(ref_q[:, :1] + 1e-300)
    close = np.minimum(np.abs(quats - ref_q).max(1), np.abs(quats + ref_q).max(1))
    assert close.max() < 1e-9
    assert np.allclose(quaternion_to_matrix(torch.as_tensor(quats)).numpy(), ref.as_matrix(), atol=1e-12)
    back = axis_angle_to_matrix(matrix_to_axis_angle(mats))
    assert torch.allclose(back, mats, atol=1e-9)


def test_axis_angle_gradient_is_finite_at_zero():
    aa = torch.zeros(2, 3, dtype=torch.float64, requires_grad=True)
    axis_angle_to_matrix(aa).sum().backward()
    assert torch.isfinite(aa.grad).all()


def _random_transforms(batch, joints, seed=0):
    rng = np.random.default_rng(seed)
    out = np.tile(np.eye(4), (batch, joints, 1, 1))
    out[..., :3, :3] = (
        Rotation.from_rotvec(rng.normal(0, 0.6, (batch * joints, 3))).as_matrix().reshape(batch, joints, 3, 3)
    )
    out[..., :3, 3] = rng.normal(0, 0.5, (batch, joints, 3))
    return torch.as_tensor(out)


def test_skin_points_one_hot_is_rigid_and_inverse_roundtrips():
    rng = np.random.default_rng(1)
    transforms = _random_transforms(3, 24)
    points = torch.as_tensor(rng.normal(0, 1, (200, 3)))
    owner = rng.integers(0, 24, 200)
    one_hot = torch.nn.functional.one_hot(torch.as_tensor(owner), 24).double()
    skinned = skin_points(points, one_hot, transforms)
    expected = (transforms[:, owner, :3, :3] @ points[None, :, :, None]).squeeze(-1) + transforms[
        :, owner, :3, 3
    ]
    assert torch.allclose(skinned, expected, atol=1e-12)
    soft = torch.as_tensor(rng.dirichlet(np.ones(4) * 0.5, 200))
    weights = torch.zeros(200, 24, dtype=torch.float64)
    weights.scatter_(1, torch.as_tensor(rng.integers(0, 24, (200, 4))), soft)
    weights /= weights.sum(1, keepdim=True)
    posed = skin_points(points, weights, transforms)
    back = skin_points(posed, weights, transforms, inverse=True)
    assert torch.allclose(back, points.expand(3, -1, -1), atol=1e-9)


def test_skin_rotations_matrices_and_quaternions():
    rng = np.random.default_rng(2)
    transforms = _random_transforms(2, 24, seed=3)
    rots = torch.as_tensor(Rotation.random(50, random_state=4).as_matrix())
    owner = torch.as_tensor(rng.integers(0, 24, 50))
    one_hot = torch.nn.functional.one_hot(owner, 24).double()
    out = skin_rotations(rots, one_hot, transforms)
    assert torch.allclose(out, transforms[:, owner, :3, :3] @ rots, atol=1e-10)
    quats = matrix_to_quaternion(rots)
    out_q = skin_rotations(quats, one_hot, transforms)
    assert out_q.shape == (2, 50, 4)
    assert torch.allclose(quaternion_to_matrix(out_q), out, atol=1e-10)
    # Blended weights (up to 4 joints, as skinning weights are): still a proper rotation, and the
    # inverse undoes it.
    weights = torch.zeros(50, 24, dtype=torch.float64)
    weights.scatter_(
        1, torch.as_tensor(rng.integers(0, 24, (50, 4))), torch.as_tensor(rng.dirichlet(np.ones(4), 50))
    )
    weights /= weights.sum(1, keepdim=True)
    blended = skin_rotations(rots, weights, transforms)
    eye = torch.eye(3, dtype=torch.float64)
    assert torch.allclose(blended @ blended.transpose(-1, -2), eye.expand_as(blended), atol=1e-9)
    assert torch.allclose(torch.linalg.det(blended), torch.ones(2, 50, dtype=torch.float64), atol=1e-9)
    back = skin_rotations(blended, weights, transforms, inverse=True)
    assert torch.allclose(back, rots.expand(2, -1, -1, -1), atol=1e-9)
    # It is the nearest rotation: no rotation from scipy's polar decomposition is closer.
    from scipy.linalg import polar

    from stg_node.body import blend_transforms

    linear = blend_transforms(weights, transforms)[..., :3, :3].numpy()
    polar_factor = np.stack([[polar(m)[0] for m in batch] for batch in linear])
    assert np.allclose(blended.numpy(), polar_factor @ rots.numpy(), atol=1e-9)


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    path = tmp_path_factory.mktemp("lbs") / "SMPL_NEUTRAL.npz"
    write_smpl_npz(path, random_smpl_arrays(seed=9, num_verts=300))
    return load_body_model(path, dtype=torch.float64)


def test_big_pose_matches_gauhuman_definition(model):
    flat = np.asarray(BIG_POSE).reshape(72)
    expected = np.zeros(72)
    expected[5], expected[8] = np.deg2rad(45), -np.deg2rad(45)
    expected[23], expected[26] = -np.deg2rad(30), np.deg2rad(30)
    assert np.allclose(flat, expected)
    joints = big_pose_output(model).joints[0]
    rest = model.rest_joints()[0]
    assert joints[7, 0] > rest[7, 0] + 0.1 and joints[8, 0] < rest[8, 0] - 0.1  # ankles spread apart


def test_canonical_transforms_carry_big_pose_to_posed_world(model):
    rng = np.random.default_rng(5)
    betas = torch.as_tensor(rng.normal(0, 1, (2, 10)))
    poses = torch.as_tensor(rng.normal(0, 0.5, (2, 72)))
    Rh, Th = torch.as_tensor(rng.normal(0, 1, (2, 3))), torch.as_tensor(rng.normal(0, 1, (2, 3)))
    transforms = canonical_transforms(model, betas, poses, Rh, Th)
    canonical_joints = big_pose_output(model, betas).joints
    posed = model(betas, poses, Rh, Th, pose_blendshapes=False)
    # A point attached to joint j (one-hot weight) lands where the pose puts that joint.
    one_hot = torch.eye(24, dtype=torch.float64)
    moved = torch.stack(
        [skin_points(canonical_joints[b], one_hot, transforms[b : b + 1])[0] for b in range(2)]
    )
    assert torch.allclose(moved, posed.joints, atol=1e-9)
    # The per-joint inverses and skin_points(inverse=True) both undo it.
    inverse = canonical_transforms(model, betas, poses, Rh, Th, inverse=True)
    assert torch.allclose(
        inverse @ transforms, torch.eye(4, dtype=torch.float64).expand_as(transforms), atol=1e-9
    )
    canonical_verts = big_pose_output(model, betas).vertices
    weights = model.weights
    there = torch.stack(
        [skin_points(canonical_verts[b], weights, transforms[b : b + 1])[0] for b in range(2)]
    )
    back = torch.stack(
        [skin_points(there[b], weights, transforms[b : b + 1], inverse=True)[0] for b in range(2)]
    )
    assert torch.allclose(back, canonical_verts, atol=1e-9)


def test_nearest_vertex_weights(model):
    verts = model.v_template
    points = verts[:40] + 1e-4
    assert torch.equal(nearest_vertex_weights(points, verts, model.weights, chunk=16), model.weights[:40])
