"""The fit's depth-order test (FitConfig.order_test_bones): the other depth order of a limb bone
keeps the picture (closed-form projective geometry), and a limb held on the wrong side of the
image plane by the temporal term is turned back where the fit's own cost says so."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from trackhelpers import GroundTruth, projected_keypoints

from stg_node.body.lbs import matrix_to_axis_angle
from stg_node.data.synth.joint_limits import euler_to_smpl_pose
from stg_node.tracking.evaluation import joints_from_params
from stg_node.tracking.fitting import DTYPE, FACING_CAMERA, FitConfig, SmplFitter
from stg_node.tracking.layouts import get_layout

LEFT_UPPER_ARM = (16, 18)
SIZE = 256


def reaching_pose() -> np.ndarray:
    """(24, 3) SMPL pose: the left arm swung 60 degrees forward (towards a camera the body faces)
    and lowered 30; the right arm lowered; the left elbow a little bent."""
    euler = np.zeros((24, 3))
    euler[16] = (0.0, -60.0, -30.0)
    euler[17] = (0.0, 0.0, 60.0)
    euler[18] = (0.0, -20.0, 0.0)
    return euler_to_smpl_pose(euler)


def still_subject(frames: int = 3) -> GroundTruth:
    """The reaching pose, held, 3 m in front of a 256 px camera (60 degree field of view), facing it."""
    focal = (SIZE / 2) / np.tan(np.radians(30.0))
    K = np.array([[focal, 0.0, SIZE / 2], [0.0, focal, SIZE / 2], [0.0, 0.0, 1.0]])
    Rh = matrix_to_axis_angle(torch.as_tensor(FACING_CAMERA)).numpy()
    return GroundTruth(
        K=K, R=np.eye(3), t=np.zeros(3), size=SIZE,
        poses=np.repeat(reaching_pose()[None], frames, axis=0),
        Rh=np.repeat(Rh[None], frames, axis=0), Th=np.repeat([[0.0, 0.2, 3.0]], frames, axis=0),
        betas=np.zeros(10), folder=None,
    )  # fmt: skip


def joints_of(body, poses, Rh, Th) -> np.ndarray:
    return joints_from_params(body, np.asarray(poses).reshape(1, 72), np.asarray(Rh)[None],
                              np.asarray(Th)[None], np.zeros((1, 10)))[0]  # fmt: skip


def towards_camera(joints: np.ndarray, bone) -> float:
    """How far the bone's far end lies nearer the camera than its near end (sine of its lean)."""
    j, c = bone
    d = joints[c] - joints[j]
    return float(-(d / np.linalg.norm(d)) @ (joints[j] / np.linalg.norm(joints[j])))


def theta_of(truth: GroundTruth) -> torch.Tensor:
    """The fitter's parameter vector for the truth, with FACING_CAMERA as its base rotation."""
    return torch.as_tensor(
        np.concatenate([np.zeros(3), truth.Th[0], truth.poses[0, 1:].reshape(69)]), dtype=DTYPE
    )


def context() -> dict:
    return {"base_rotation": torch.as_tensor(FACING_CAMERA, dtype=DTYPE),
            "betas": torch.zeros(1, 10, dtype=DTYPE), "calibrating": False}  # fmt: skip


def test_the_other_depth_order_keeps_the_pixels_and_the_length(body):
    truth = still_subject(1)
    fitter = SmplFitter(body, get_layout("smpl24"), truth.K, FitConfig(), betas=np.zeros(10))
    theta = theta_of(truth)
    flipped = fitter._depth_flipped(theta, context(), LEFT_UPPER_ARM)
    assert flipped is not None
    Rh = truth.Rh[0]
    before = joints_of(body, truth.poses[0], Rh, truth.Th[0])
    after = joints_of(body, np.concatenate([np.zeros(3), flipped[6:].numpy()]), Rh, flipped[3:6].numpy())
    shoulder, elbow = LEFT_UPPER_ARM

    def pixel(p):
        return truth.K[:2, :2] @ (p[:2] / p[2]) + truth.K[:2, 2]

    assert np.allclose(pixel(after[elbow]), pixel(before[elbow]), atol=1e-4)  # the same picture
    assert np.linalg.norm(after[elbow] - after[shoulder]) == pytest.approx(
        np.linalg.norm(before[elbow] - before[shoulder]), rel=1e-5
    )
    # The elbow on its ray at the other root of |s u - shoulder| = length: s = 2 u.shoulder - |elbow|.
    ray = before[elbow] / np.linalg.norm(before[elbow])
    other = (2.0 * ray @ before[shoulder] - np.linalg.norm(before[elbow])) * ray
    assert np.allclose(after[elbow], other, atol=1e-5)
    assert towards_camera(before, LEFT_UPPER_ARM) > 0.5 and towards_camera(after, LEFT_UPPER_ARM) < -0.5
    untouched = [k for k in range(24) if k not in (18, 20, 22)]  # the arm below the elbow moves with it
    assert np.allclose(after[untouched], before[untouched], atol=1e-6)
    forearm = (before[20] - before[18], after[20] - after[18])  # keeps its orientation in the camera's frame
    assert np.allclose(forearm[0], forearm[1], atol=1e-6)
    # A bone in the image plane has no other order to try.
    level = theta.clone()
    level[6 + 3 * 15 : 6 + 3 * 16] = 0.0  # the left shoulder at rest: the arm straight out sideways
    assert fitter._depth_flipped(level, context(), LEFT_UPPER_ARM) is None


@pytest.mark.parametrize("bones, turned_back", [((), False), ((LEFT_UPPER_ARM,), True)])
def test_a_limb_held_behind_by_the_temporal_term_is_turned_back_by_the_test(body, bones, turned_back):
    """The tracked state has the left arm reaching away from the camera (60 degrees backwards,
    past the shoulder's range); the keypoints cannot tell. The temporal term keeps the wrong order;
    the depth-order test finds the other one cheaper (the joint limits) and takes it."""
    truth = still_subject(3)
    layout = get_layout("smpl24")
    fitter = SmplFitter(body, layout, truth.K, FitConfig(order_test_bones=bones), betas=np.zeros(10))
    keypoints = projected_keypoints(body, layout, truth, 0)
    assert fitter.fit(keypoints, 0.0) is not None
    wrong = fitter._depth_flipped(theta_of(truth), context(), LEFT_UPPER_ARM)
    fitter._rotation, fitter._translation = FACING_CAMERA.copy(), wrong[3:6].numpy().copy()
    fitter._pose = wrong[6:].numpy().copy()
    for i in (1, 2):
        result = fitter.fit(projected_keypoints(body, layout, truth, i), i / 30.0)
    fitted = joints_of(body, result.poses.reshape(72), result.Rh, result.Th)
    lean = towards_camera(fitted, LEFT_UPPER_ARM)
    true_lean = towards_camera(joints_of(body, truth.poses[0], truth.Rh[0], truth.Th[0]), LEFT_UPPER_ARM)
    assert bool(np.sign(lean) == np.sign(true_lean)) is turned_back, (lean, true_lean)


@pytest.mark.parametrize("bones", [((0, 1),), ((16, 24),), ((16,),)])
def test_bones_outside_the_body_joints_are_refused(bones):
    with pytest.raises(ValueError, match="order_test_bones"):
        FitConfig(order_test_bones=bones).validate()
