"""The shipped open body: SMPL conventions, closed-form poses, no tearing, human proportions."""

from __future__ import annotations

import collections
import types

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from stg_node.body import OPEN_BODY_FILE, SMPL_PARENTS, load_body_model, skin_points


@pytest.fixture(scope="module")
def body():
    return load_body_model(None, dtype=torch.float64)


def _pose(**joint_rotvecs_deg) -> torch.Tensor:
    """A (1, 72) pose from {joint index as 'j16': (x, y, z) degrees}."""
    pose = np.zeros((24, 3))
    for key, value in joint_rotvecs_deg.items():
        pose[int(key[1:])] = np.deg2rad(value)
    return torch.as_tensor(pose.reshape(1, 72))


def test_asset_is_small_and_loads_by_name(body):
    assert OPEN_BODY_FILE.stat().st_size < 4e6
    assert load_body_model("open").num_vertices == body.num_vertices
    assert body.name == "open_body" and body.num_betas == 10 and not body.has_pose_blendshapes
    assert torch.equal(body.parents, torch.as_tensor(SMPL_PARENTS))
    assert body.uv is not None and float(body.uv.min()) >= 0 and float(body.uv.max()) <= 1
    assert body.uv_faces.shape == body.faces.shape and int(body.uv_faces.max()) < body.uv.shape[0]
    assert body.texture.dtype == np.uint8 and body.texture.shape[2] == 3
    assert body.texture.std() > 20  # a pattern, not a flat colour


def test_zero_pose_gives_rest_joints(body):
    with np.load(OPEN_BODY_FILE) as data:
        stored_joints = torch.as_tensor(data["J"], dtype=torch.float64)
    out = body()
    assert torch.allclose(out.joints[0], body.J_regressor @ body.v_template, atol=1e-9)
    assert torch.allclose(out.joints[0], stored_joints, atol=1e-5)
    assert torch.allclose(out.vertices[0], body.v_template, atol=1e-9)
    eye = torch.eye(4, dtype=torch.float64)
    assert torch.allclose(out.bone_transforms[0], eye.expand(24, 4, 4), atol=1e-9)


def test_smpl_conventions(body):
    joints = body.rest_joints()[0].numpy()
    verts = body.v_template.numpy()
    # Y up: head above neck above pelvis above knees above ankles.
    assert joints[15, 1] > joints[12, 1] > joints[9, 1] > joints[0, 1] > joints[4, 1] > joints[7, 1]
    # SMPL's left (odd hips/knees..., even arms...) is +x: left joints mirror the right ones.
    for left, right in [(1, 2), (4, 5), (7, 8), (10, 11), (13, 14), (16, 17), (18, 19), (20, 21), (22, 23)]:
        assert joints[left, 0] > 0.05 and np.allclose(joints[left] * [-1, 1, 1], joints[right], atol=5e-3)
    # Facing +z: toes (feet joints) are in front of the ankles, the nose in front of the head joint.
    assert joints[10, 2] > joints[7, 2] + 0.08
    head_verts = verts[body.weights.numpy()[:, 15] > 0.9]
    assert head_verts[:, 2].max() > joints[15, 2] + 0.07
    # T-pose: arm joints level with the shoulders and straight out.
    arm = joints[[16, 18, 20, 22]]
    assert np.ptp(arm[:, 1]) < 0.03 and np.ptp(arm[:, 2]) < 0.03 and np.all(np.diff(arm[:, 0]) > 0.05)
    # Legs straight down.
    leg = joints[[1, 4, 7]]
    assert np.ptp(leg[:, 0]) < 0.02 and np.ptp(leg[:, 2]) < 0.02
    # Weights: rows sum to 1, each joint drives some vertices.
    weights = body.weights.numpy()
    assert np.allclose(weights.sum(1), 1, atol=1e-5) and np.all(weights.max(0) > 0.3)


def test_human_proportions(body):
    verts = body.v_template.numpy()
    height = np.ptp(verts[:, 1])
    span = np.ptp(verts[:, 0])  # fingertip to fingertip in the T-pose
    assert 1.6 <= height <= 1.9
    assert abs(span / height - 1.0) < 0.08
    # Taller with the height direction, as SMPL's first beta roughly is.
    taller = body(betas=torch.tensor([2.0])).vertices[0].numpy()
    assert np.ptp(taller[:, 1]) > height + 0.05


def _closed_form_arm(joints, chain, rotations):
    """Positions of the joints in ``chain`` after rotating each by ``rotations`` (world = local
    here since parents up to the chain's start are unrotated), by direct composition."""
    out = [joints[chain[0]]]
    acc = Rotation.identity()
    for k in range(1, len(chain)):
        acc = acc * rotations[k - 1]
        out.append(out[-1] + acc.apply(joints[chain[k]] - joints[chain[k - 1]]))
    return np.array(out)


def test_elbow_at_90_degrees(body):
    joints = body.rest_joints()[0].numpy()
    out = body(poses=_pose(j18=(0, -90, 0)))  # left elbow: forearm swings to the front (+z)
    posed = out.joints[0].numpy()
    forearm = joints[20] - joints[18]
    expected_wrist = joints[18] + np.array([0, 0, np.linalg.norm(forearm)])
    assert np.allclose(posed[20], expected_wrist, atol=2e-3)
    assert np.allclose(posed[:19], joints[:19], atol=1e-9)  # nothing upstream moved
    # A vertex wholly on the forearm turns rigidly about the elbow.
    weights = body.weights.numpy()
    rigid = np.flatnonzero(weights[:, 18] > 0.999)
    rot = Rotation.from_rotvec([0, -np.pi / 2, 0])
    expected = joints[18] + rot.apply(body.v_template.numpy()[rigid] - joints[18])
    assert np.allclose(out.vertices[0].numpy()[rigid], expected, atol=1e-9)


def test_raised_arm_and_global_transform(body):
    joints = body.rest_joints()[0].numpy()
    pose = _pose(j16=(0, 0, 90), j17=(0, 0, -90))  # both arms straight up
    Rh = np.array([0.0, np.pi / 2, 0.0])
    Th = np.array([0.5, 0.0, -1.0])
    out = body(poses=pose, Rh=torch.as_tensor(Rh)[None], Th=torch.as_tensor(Th)[None])
    for chain, rot in (([16, 18, 20, 22], (0, 0, 90)), ([17, 19, 21, 23], (0, 0, -90))):
        local = _closed_form_arm(
            joints, chain, [Rotation.from_euler("xyz", rot, degrees=True)] + [Rotation.identity()] * 2
        )
        assert np.allclose(local[1:3, 0], local[0, 0], atol=2e-3)  # elbow, wrist straight above the shoulder
        world = Rotation.from_rotvec(Rh).apply(local) + Th
        assert np.allclose(out.joints[0, chain].numpy(), world, atol=2e-3)


def _edges(faces: np.ndarray) -> np.ndarray:
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(edges, axis=1), axis=0)


def _stress_poses() -> torch.Tensor:
    rng = np.random.default_rng(0)
    poses = [rng.normal(0, 0.35, (24, 3)) for _ in range(6)]  # everyday random poses
    extreme = np.zeros((6, 24, 3))
    extreme[0, [18, 19], 1] = np.deg2rad([-150, 150])  # elbows fully bent
    extreme[1, [4, 5], 0] = np.deg2rad(150)  # knees fully bent
    extreme[2, [1, 2], 0] = np.deg2rad(-120)  # hips flexed (sitting on the floor)
    extreme[2, [4, 5], 0] = np.deg2rad(120)
    extreme[3, [16, 17], 2] = np.deg2rad([80, -80])  # arms up
    extreme[3, [13, 14], 2] = np.deg2rad([20, -20])
    extreme[4, [3, 6, 9], 1] = np.deg2rad(30)  # trunk twisted 90 degrees
    extreme[4, [12, 15], 0] = np.deg2rad(35)  # head bowed
    extreme[5, [16, 17], 2] = np.deg2rad([-80, 80])  # arms down along the body
    extreme[5, [20, 21], 0] = np.deg2rad(70)  # wrists bent
    extreme[5, [7, 8], 0] = np.deg2rad(40)  # feet pointed
    return torch.as_tensor(np.concatenate([np.stack(poses), extreme]).reshape(-1, 72))


def _stretch(rest: np.ndarray, posed: np.ndarray, edges: np.ndarray):
    """Per edge: length ratio posed/rest and absolute growth in metres."""
    rest_len = np.linalg.norm(rest[edges[:, 0]] - rest[edges[:, 1]], axis=1)
    posed_len = np.linalg.norm(posed[edges[:, 0]] - posed[edges[:, 1]], axis=1)
    return posed_len / rest_len.clip(1e-9), posed_len - rest_len, rest_len


# Bounds for "no tearing": plain LBS stretches skin at bent joints (armpits under random arm and
# collar poses, the crotch, the back of a fully bent knee: up to ~3.4x / 6 cm on 2.5 cm edges
# here), but a tear (vertices left behind by a wrong weight) opens gaps of tens of centimetres,
# which test_wrong_weights_would_tear checks these bounds catch.
MAX_RATIO = 4.0  # for edges of at least 1 cm (millimetre face/crotch edges excluded)
MAX_GROWTH_M = 0.08  # for every edge; inside a bend, edges may fold to a few % of their length


def test_skinning_does_not_tear(body):
    edges = _edges(body.faces.numpy())
    rest = body.v_template.numpy()
    verts = body(poses=_stress_poses()).vertices.numpy()
    for k, posed in enumerate(verts):
        ratio, growth, rest_len = _stretch(rest, posed, edges)
        sized = ratio[rest_len >= 1e-2]
        assert sized.max() < MAX_RATIO, f"pose {k}: an edge stretched {sized.max():.1f}x"
        assert growth.max() < MAX_GROWTH_M, f"pose {k}: an edge grew by {growth.max() * 100:.1f} cm (tearing)"
        assert sized.min() > 0.03, f"pose {k}: an edge collapsed to {sized.min():.2f} of its length"
        assert np.percentile(ratio, 99) < 2.0 and np.median(ratio) == pytest.approx(1.0, abs=0.05)


def test_wrong_weights_would_tear(body):
    """The tearing check has teeth: moving one region's weights to a wrong joint breaks it."""
    weights = body.weights.clone()
    forearm = weights[:, 18] > 0.5
    weights[forearm] = 0
    weights[forearm, 9] = 1.0  # forearm glued to the chest
    edges = _edges(body.faces.numpy())
    out = body(poses=_pose(j16=(0, 0, 80)))
    posed = skin_points(body.v_template, weights, out.bone_transforms)[0].numpy()
    ratio, growth, rest_len = _stretch(body.v_template.numpy(), posed, edges)
    assert growth.max() > MAX_GROWTH_M and ratio[rest_len >= 1e-2].max() > MAX_RATIO


def test_open_body_matches_smplx(body):
    """smplx (an independent SMPL implementation) loads the open body's arrays and agrees."""
    import smplx

    with np.load(OPEN_BODY_FILE) as data:
        struct_ = types.SimpleNamespace(**{k: data[k] for k in data.files})
    oracle = smplx.SMPL(
        model_path=None, data_struct=struct_, num_betas=10, dtype=torch.float64,
        vertex_ids=collections.defaultdict(int), create_transl=False,
    )  # fmt: skip
    rng = np.random.default_rng(2)
    betas = torch.as_tensor(rng.normal(0, 1, (2, 10)))
    poses = torch.as_tensor(rng.normal(0, 0.5, (2, 72)))
    ours = body(betas=betas, poses=poses)
    ref = oracle(betas=betas, global_orient=poses[:, :3], body_pose=poses[:, 3:])
    assert torch.allclose(ours.vertices, ref.vertices, atol=1e-5)
    assert torch.allclose(ours.joints, ref.joints[:, :24], atol=1e-5)
