"""The Tracker (PoseEstimator): confidence when the person is there, lost, doubled or garbled; never a
wild pose; and the whole chain with the real detector where it is installed."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from trackhelpers import camera_joints, needs_blazepose, projected_keypoints

from stg_node.body.lbs import axis_angle_to_matrix
from stg_node.data.io import read_image
from stg_node.tracking.camera import Intrinsics
from stg_node.tracking.evaluation import joints_from_params, mpjpe
from stg_node.tracking.layouts import get_layout
from stg_node.tracking.masks import PlateMasker
from stg_node.tracking.priors import limit_excess
from stg_node.tracking.tracker import Tracker, TrackerConfig
from stg_node.tracking.types import Keypoints


class ScriptedDetector:
    """Returns whatever the test queued for each frame (Keypoints or None)."""

    layout = "blazepose33"

    def __init__(self):
        self.queue: list[Keypoints | None] = []

    def reset(self):
        pass

    def __call__(self, image):
        return self.queue.pop(0)


def _tracker(body, truth, **config):
    intrinsics = Intrinsics(truth.K, None, truth.size, truth.size, "test")
    detector = ScriptedDetector()
    return Tracker(detector, body, intrinsics, TrackerConfig(**config)), detector


def _frame(truth, i):
    return read_image(truth.folder / "Camera_B1" / f"{i:06d}.png")


def _limit_excess_deg(smpl) -> float:
    """Largest excursion beyond the joint limits, degrees (either Euler branch, as priors.py)."""
    rotations = axis_angle_to_matrix(torch.as_tensor(smpl.poses[1:], dtype=torch.float64))
    return float(np.rad2deg(limit_excess(rotations).max().item()))


def test_tracker_is_a_pose_estimator_and_follows_the_person(body, synth_small):
    tracker, detector = _tracker(body, synth_small)
    layout = get_layout("blazepose33")
    rng = np.random.default_rng(0)
    estimates = []
    for i in range(len(synth_small)):
        detector.queue.append(projected_keypoints(body, layout, synth_small, i, noise_px=1.0, rng=rng))
        estimates.append(tracker.estimate(_frame(synth_small, i), i / 30.0))
    confidence = np.array([e.confidence for e in estimates])
    assert confidence.min() > 0.5 and np.median(confidence) > 0.8
    smpl = [e.smpl for e in estimates]
    pred = joints_from_params(
        body,
        np.stack([s.poses.reshape(72) for s in smpl]),
        np.stack([s.Rh for s in smpl]),
        np.stack([s.Th for s in smpl]),
        np.stack([s.betas for s in smpl]),
    )
    assert mpjpe(pred, camera_joints(body, synth_small)).mean() < 0.06  # smoothed: a little lag
    assert all(e.mask.shape == (synth_small.size, synth_small.size) for e in estimates)
    assert all(np.all(s.poses[0] == 0) for s in smpl)


def test_lost_person_gives_zero_confidence_and_holds_the_last_pose(body, synth_small):
    tracker, detector = _tracker(body, synth_small)
    layout = get_layout("blazepose33")
    for i in range(5):
        detector.queue.append(projected_keypoints(body, layout, synth_small, i))
        good = tracker.estimate(_frame(synth_small, i), i / 30.0)
    detector.queue.append(None)
    lost = tracker.estimate(_frame(synth_small, 5), 5 / 30.0)
    assert lost.confidence == 0.0 and "no_person" in lost.flags
    assert np.array_equal(lost.smpl.poses, good.smpl.poses) and np.array_equal(lost.smpl.Th, good.smpl.Th)
    assert not lost.mask.any()
    # Too few points (only a face): no fit, still a held pose.
    face = projected_keypoints(body, layout, synth_small, 6)
    score = np.zeros(33, np.float32)
    score[:5] = 1.0
    detector.queue.append(dataclasses.replace(face, score=score))
    partial = tracker.estimate(_frame(synth_small, 6), 6 / 30.0)
    assert partial.confidence == 0.0 and "too_few_keypoints" in partial.flags
    # Back again: re-initialised, confident.
    detector.queue.append(projected_keypoints(body, layout, synth_small, 7))
    assert tracker.estimate(_frame(synth_small, 7), 7 / 30.0).confidence > 0.5


def test_empty_frames_from_the_start_give_a_rest_pose_facing_the_camera(body, synth_small):
    tracker, detector = _tracker(body, synth_small)
    detector.queue.append(None)
    empty = tracker.estimate(np.zeros((synth_small.size, synth_small.size, 3), np.uint8), 0.0)
    assert empty.confidence == 0.0 and np.all(empty.smpl.poses == 0)
    assert empty.smpl.Th[2] > 0  # in front of the camera


def test_two_people_lower_the_confidence(body, synth_small):
    tracker, detector = _tracker(body, synth_small)
    layout = get_layout("blazepose33")
    detector.queue.append(projected_keypoints(body, layout, synth_small, 0))
    single = tracker.estimate(_frame(synth_small, 0), 0.0)
    detector.queue.append(dataclasses.replace(projected_keypoints(body, layout, synth_small, 1), people=2))
    double = tracker.estimate(_frame(synth_small, 1), 1 / 30.0)
    assert single.confidence > 0.8 and double.confidence < 0.2 and "multiple_people" in double.flags


def test_garbage_keypoints_give_low_confidence_and_an_anatomical_pose(body, synth_small):
    tracker, detector = _tracker(body, synth_small)
    rng = np.random.default_rng(5)
    for i in range(6):
        xy = rng.uniform(0, synth_small.size, size=(33, 2)).astype(np.float32)
        detector.queue.append(Keypoints(layout="blazepose33", xy=xy, score=np.ones(33, np.float32)))
        estimate = tracker.estimate(_frame(synth_small, i), i / 30.0)
        assert estimate.confidence < 0.3, estimate.confidence
        assert _limit_excess_deg(estimate.smpl) < 5.0, _limit_excess_deg(estimate.smpl)
        assert np.all(np.isfinite(estimate.smpl.Th)) and 0 < estimate.smpl.Th[2] < 60


def test_frames_of_the_wrong_size_or_type_are_refused(body, synth_small):
    tracker, _ = _tracker(body, synth_small)
    with pytest.raises(ValueError, match="intrinsics are for"):
        tracker.estimate(np.zeros((10, 10, 3), np.uint8), 0.0)
    with pytest.raises(ValueError, match="uint8"):
        tracker.estimate(np.zeros((synth_small.size, synth_small.size, 3), np.float32), 0.0)
    with pytest.raises(ValueError, match="timestamp"):
        tracker.estimate(np.zeros((synth_small.size, synth_small.size, 3), np.uint8), float("nan"))


def test_masks_keep_only_the_part_touching_the_person(body, synth_small):
    rng = np.random.default_rng(2)
    plate = rng.integers(90, 170, size=(synth_small.size // 8, synth_small.size // 8, 3), dtype=np.uint8)
    plate = np.kron(plate, np.ones((8, 8, 1), np.uint8))  # a blocky wall
    intrinsics = Intrinsics(synth_small.K, None, synth_small.size, synth_small.size, "test")
    detector = ScriptedDetector()
    tracker = Tracker(detector, body, intrinsics, TrackerConfig(), PlateMasker(plate))
    truth = read_image(synth_small.folder / "mask" / "Camera_B1" / "000000.png")[..., 0] > 0
    frame = np.where(truth[..., None], _frame(synth_small, 0), plate)  # the person in front of the wall
    frame[5:25, 5:25] = 250  # a bright object in a corner, away from the person
    detector.queue.append(projected_keypoints(body, get_layout("blazepose33"), synth_small, 0))
    estimate = tracker.estimate(frame, 0.0)
    mask = estimate.mask > 0
    assert not mask[5:25, 5:25].any()
    assert (mask & truth).sum() / (mask | truth).sum() > 0.9


@needs_blazepose
def test_real_chain_on_synthetic_video_frames(body, synth_small):
    from stg_node.tracking.detectors import make_detector

    intrinsics = Intrinsics(synth_small.K, None, synth_small.size, synth_small.size, "test")
    tracker = Tracker(make_detector("blazepose"), body, intrinsics)
    estimates = [tracker.estimate(_frame(synth_small, i), i / 30.0) for i in range(len(synth_small))]
    assert np.median([e.confidence for e in estimates]) > 0.6
    truth = read_image(synth_small.folder / "mask" / "Camera_B1" / "000010.png")[..., 0] > 0
    mask = estimates[10].mask > 0
    assert (mask & truth).sum() / (mask | truth).sum() > 0.85
    # Empty frames after the person: confidence 0, the pose held.
    blank = np.zeros_like(_frame(synth_small, 0))
    lost = tracker.estimate(blank, len(synth_small) / 30.0)
    assert lost.confidence == 0.0 and np.array_equal(lost.smpl.poses, estimates[-1].smpl.poses)
