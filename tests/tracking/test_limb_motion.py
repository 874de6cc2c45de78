"""The fit's per-joint temporal term (opt-in): a fast limb with exact keypoints is followed, a still
limb with jittered keypoints is held (limb_motion.py, FitConfig.temporal_max_rad_per_s)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from trackhelpers import GroundTruth, projected_keypoints

from stg_node.body.lbs import axis_angle_to_matrix
from stg_node.tracking.body_points import BodyKeypoints
from stg_node.tracking.fitting import FitConfig, SmplFitter
from stg_node.tracking.layouts import get_layout
from stg_node.tracking.limb_motion import LimbMotion

FPS = 30.0
L_SHOULDER, L_ELBOW = 16, 18


def _model(body, layout_name="smpl24"):
    layout = get_layout(layout_name)
    return layout, BodyKeypoints(body, [t.point for t in layout.targets]).double()


def test_a_segment_turned_in_the_image_reads_its_chord_angle_and_jitter_reads_nothing(body):
    layout, model = _model(body)
    motion = LimbMotion(model)
    names = [t.point.name for t in layout.targets]
    elbow, wrist = names.index("left_elbow"), names.index("left_wrist")
    # A still body whose left forearm (elbow -> wrist, 60 px) turns 0.4 rad about the elbow.
    rng = np.random.default_rng(0)
    before = rng.uniform(50, 200, (len(names), 2))
    before[wrist] = before[elbow] + [60.0, 0.0]
    after = before.copy()
    angle = 0.4
    after[wrist] = before[elbow] + 60.0 * np.array([math.cos(angle), math.sin(angle)])
    ok = np.ones(len(names), bool)
    turn = motion.turn(before, ok, after, ok, jitter_px=0.0, min_length_px=1.0)
    assert turn[L_ELBOW - 1] == pytest.approx(2 * math.sin(angle / 2), rel=1e-9)  # chord / length
    # The elbow's parents see the wrist move too; joints whose points did not move see nothing.
    assert turn[L_SHOULDER - 1] > 0
    assert turn[19 - 1] == 0.0 and turn[1 - 1] == 0.0  # the right elbow, the left hip
    # The whole body carried 30 px sideways: no joint turned.
    shifted = motion.turn(before, ok, before + [30.0, 0.0], ok, jitter_px=0.0, min_length_px=1.0)
    assert np.allclose(shifted, 0.0)
    # Displacements below the jitter allowance read as no turn; a point unusable in either frame
    # says nothing.
    jitter = rng.uniform(-1.0, 1.0, before.shape)
    assert np.all(motion.turn(before, ok, before + jitter, ok, jitter_px=3.0, min_length_px=1.0) == 0.0)
    lost = ok.copy()
    lost[wrist] = False
    assert motion.turn(before, ok, after, lost, jitter_px=0.0, min_length_px=1.0)[L_ELBOW - 1] == 0.0


def _facing_camera_truth(poses: np.ndarray) -> GroundTruth:
    n = len(poses)
    return GroundTruth(
        K=np.array([[300.0, 0.0, 128.0], [0.0, 300.0, 128.0], [0.0, 0.0, 1.0]]),
        R=np.eye(3),
        t=np.zeros(3),
        size=256,
        poses=poses,
        Rh=np.tile([math.pi, 0.0, 0.0], (n, 1)),  # SMPL's up to the image's up, its front to the camera
        Th=np.tile([0.0, 0.2, 3.0], (n, 1)),
        betas=np.zeros(10),
        folder=None,
    )


def _track(body, truth, config, noise_px=0.0):
    layout = get_layout("smpl24")
    fitter = SmplFitter(body, layout, truth.K, config, betas=np.zeros(10))
    rng = np.random.default_rng(1)
    fitted = []
    for i in range(len(truth)):
        result = fitter.fit(projected_keypoints(body, layout, truth, i, noise_px=noise_px, rng=rng), i / FPS)
        assert result is not None
        fitted.append(result.poses)
    return np.stack(fitted)


def _angle_deg(a, b) -> np.ndarray:
    ra = axis_angle_to_matrix(torch.as_tensor(a, dtype=torch.float64))
    rb = axis_angle_to_matrix(torch.as_tensor(b, dtype=torch.float64))
    cos = ((ra.transpose(-1, -2) @ rb).diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
    return np.degrees(np.arccos(np.clip(cos.numpy(), -1.0, 1.0)))


FIXED = FitConfig()  # the default: one plausible speed for every joint
ADAPTIVE = dataclasses.replace(FitConfig(), temporal_max_rad_per_s=12.0)


def test_a_fast_limb_with_exact_keypoints_is_not_held_back(body):
    # The left arm swings up in the image plane at 9 rad/s (17 degrees a frame at 30 fps), three
    # times the fixed term's plausible speed; the keypoints are exact.
    frames = 10
    poses = np.zeros((frames, 24, 3))
    poses[:, L_SHOULDER, 2] = -1.2 + 0.3 * np.arange(frames)
    truth = _facing_camera_truth(poses)
    adaptive = _track(body, truth, ADAPTIVE)
    fixed = _track(body, truth, FIXED)
    late = slice(3, frames)
    err_adaptive = _angle_deg(adaptive[late, L_SHOULDER], poses[late, L_SHOULDER])
    err_fixed = _angle_deg(fixed[late, L_SHOULDER], poses[late, L_SHOULDER])
    assert err_fixed.mean() > 8.0, f"the fixed term should lag: {err_fixed.mean():.1f} deg"
    assert err_adaptive.mean() < 0.5 * err_fixed.mean(), (err_adaptive.mean(), err_fixed.mean())


def test_a_still_limb_with_jittered_keypoints_is_held_still(body):
    # Standing still, the keypoints jittered by 1.5 px (about a detector's): the arm's fitted
    # rotation moves frame to frame no more than with the fixed term.
    frames = 16
    poses = np.zeros((frames, 24, 3))
    poses[:, L_SHOULDER, 2] = -1.1
    poses[:, L_ELBOW, 1] = -0.3
    truth = _facing_camera_truth(poses)
    adaptive = _track(body, truth, ADAPTIVE, noise_px=1.5)
    fixed = _track(body, truth, FIXED, noise_px=1.5)
    for joint in (L_SHOULDER, L_ELBOW):
        step_adaptive = _angle_deg(adaptive[2:, joint], adaptive[1:-1, joint]).mean()
        step_fixed = _angle_deg(fixed[2:, joint], fixed[1:-1, joint]).mean()
        assert step_adaptive <= 1.1 * step_fixed + 0.05, (joint, step_adaptive, step_fixed)
