"""What the live views compute beyond conversions: the body's joints by forward kinematics, held
against the body model's own posing (which skins through its bone transforms), and camera
projection against OpenCV's."""

from __future__ import annotations

import cv2
import numpy as np
import torch

from stg_node.body import load_body_model
from stg_node.body.smpl_io import SMPL_PARENTS
from stg_node.bus import BodyPose, GaussianSnapshot
from stg_node.nodes.live_scene import BodySkeleton, posed_joints, project_points

RNG = np.random.default_rng(11)


def random_pose(betas) -> BodyPose:
    return BodyPose(
        poses=(RNG.normal(size=(24, 3)) * 0.4).astype(np.float32),
        Rh=RNG.normal(size=3).astype(np.float32),
        Th=RNG.normal(size=3).astype(np.float32),
        betas=np.asarray(betas, np.float32),
    )


def model_joints(body, pose: BodyPose) -> np.ndarray:
    with torch.no_grad():
        out = body(
            betas=torch.as_tensor(pose.betas)[None],
            poses=torch.as_tensor(pose.poses).reshape(1, 72),
            Rh=torch.as_tensor(pose.Rh)[None],
            Th=torch.as_tensor(pose.Th)[None],
        )
    return out.joints[0].numpy()


def test_forward_kinematics_matches_the_body_models_posed_joints():
    body = load_body_model()
    skeleton = BodySkeleton()  # the open body, shaped by each pose's betas
    for _ in range(3):
        pose = random_pose(RNG.normal(size=body.num_betas) * 0.8)
        np.testing.assert_allclose(skeleton.joints(pose), model_joints(body, pose), atol=2e-5)


def test_a_snapshots_rest_joints_win_and_a_poses_own_joints_win_over_both():
    body = load_body_model()
    betas = RNG.normal(size=body.num_betas).astype(np.float32)
    with torch.no_grad():
        rest = body.rest_joints(torch.as_tensor(betas)[None])[0].numpy()
    snapshot = GaussianSnapshot(
        format="x",
        model_version=1,
        num_gaussians=0,
        arrays={"body.rest_joints": rest, "body.parents": np.asarray(SMPL_PARENTS, np.float32)},
    )
    skeleton = BodySkeleton()
    assert skeleton.use_snapshot(snapshot)
    pose = random_pose(np.zeros(body.num_betas))  # the snapshot's shape is used, not these betas
    want = model_joints(body, random_pose_with(pose, betas))
    np.testing.assert_allclose(skeleton.joints(pose), want, atol=2e-5)
    given = RNG.normal(size=(24, 3)).astype(np.float32)
    pose.joints = given
    np.testing.assert_array_equal(skeleton.joints(pose), given)
    assert not BodySkeleton().use_snapshot(GaussianSnapshot(format="x", model_version=1, num_gaussians=0))


def random_pose_with(pose: BodyPose, betas) -> BodyPose:
    return BodyPose(poses=pose.poses, Rh=pose.Rh, Th=pose.Th, betas=np.asarray(betas, np.float32))


def test_posed_joints_of_the_rest_pose_are_the_rest_joints_moved():
    rest = RNG.normal(size=(24, 3)).astype(np.float32)
    th = np.array([0.5, -1.0, 2.0], np.float32)
    out = posed_joints(rest, SMPL_PARENTS, np.zeros((24, 3)), np.zeros(3), th)
    np.testing.assert_allclose(out, rest + th, atol=1e-6)


def test_projection_matches_opencv():
    points = RNG.normal(size=(50, 3)) + np.array([0.0, 0.0, 5.0])
    K = np.array([[400.0, 0, 320], [0, 380.0, 240], [0, 0, 1]])
    rvec = RNG.normal(size=3) * 0.2
    R, _ = cv2.Rodrigues(rvec)
    t = np.array([0.1, -0.2, 0.3])
    uv, front = project_points(points, K, R, t)
    want, _ = cv2.projectPoints(points, rvec, t, K, None)
    assert front.all()
    np.testing.assert_allclose(uv, want.reshape(-1, 2), atol=1e-6)
    behind = project_points(np.array([[0.0, 0.0, -10.0]]), K, np.eye(3), np.zeros(3))[1]
    assert not behind.any()
