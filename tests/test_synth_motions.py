"""Procedural SMPL motions: joint limits (checked with scipy), continuity, coverage, determinism."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stg_node.data.synth.joint_limits import JOINT_INDEX, JOINT_LIMITS_DEG, LIMIT_TOLERANCE_DEG
from stg_node.data.synth.motions import MOTIONS, make_motion
from stg_node.data.synth.rotations import (
    axis_angle_to_matrix,
    euler_zyx_to_matrix,
    matrix_to_axis_angle,
)

FPS = 30.0
FRAMES = 240
NOVEL_START = 192


@pytest.fixture(scope="module", params=MOTIONS)
def sequence(request):
    return request.param, make_motion(request.param, FRAMES, FPS, np.random.default_rng(7), NOVEL_START)


def _euler_candidates(rotvec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Both Z-Y-X Euler decompositions (x, y, z) in degrees of each rotation (scipy, independent code)."""
    zyx = Rotation.from_rotvec(rotvec.reshape(-1, 3)).as_euler("ZYX", degrees=True)
    first = zyx[:, ::-1]
    x, y, z = first[:, 0], first[:, 1], first[:, 2]
    wrap = lambda a: (a + 180.0) % 360.0 - 180.0  # noqa: E731
    second = np.stack([wrap(x + 180.0), wrap(180.0 - y), wrap(z + 180.0)], axis=1)
    return first.reshape(rotvec.shape), second.reshape(rotvec.shape)


def test_every_pose_respects_the_joint_limits(sequence):
    _, seq = sequence
    first, second = _euler_candidates(seq.poses.astype(np.float64))
    low = JOINT_LIMITS_DEG[..., 0] - LIMIT_TOLERANCE_DEG - 0.05
    high = JOINT_LIMITS_DEG[..., 1] + LIMIT_TOLERANCE_DEG + 0.05

    def inside(euler):
        return ((euler >= low) & (euler <= high)).all(axis=-1)

    ok = inside(first) | inside(second)  # one of the two equivalent decompositions fits
    assert ok.all(), np.argwhere(~ok)[:5]


def test_knees_and_elbows_never_hyperextend(sequence):
    _, seq = sequence
    knee = seq.euler_deg[:, [JOINT_INDEX["left_knee"], JOINT_INDEX["right_knee"]], 0]
    assert knee.min() >= 0.0
    assert seq.euler_deg[:, JOINT_INDEX["left_elbow"], 1].max() <= 0.0
    assert seq.euler_deg[:, JOINT_INDEX["right_elbow"], 1].min() >= 0.0


def test_zju_conventions_and_dtypes(sequence):
    name, seq = sequence
    assert seq.poses.shape == (FRAMES, 24, 3) and seq.poses.dtype == np.float32
    assert seq.Rh.shape == (FRAMES, 3) and seq.Th.shape == (FRAMES, 3)
    assert np.isfinite(seq.poses).all() and np.isfinite(seq.Rh).all() and np.isfinite(seq.Th).all()
    assert np.count_nonzero(seq.poses[:, 0]) == 0  # global orientation lives in Rh
    # The body stays upright (SMPL +y maps near world +z) and close to the origin.
    up = axis_angle_to_matrix(seq.Rh.astype(np.float64)) @ np.array([0.0, 1.0, 0.0])
    assert up[:, 2].min() > 0.9
    reach = 1.1 if name == "approach" else 0.8  # approach walks 1 m towards the camera and back
    assert np.linalg.norm(seq.Th[:, :2], axis=1).max() < reach
    assert seq.segments[0].start == 0 and seq.segments[-1].stop == FRAMES


def test_motion_is_continuous_across_segments(sequence):
    _, seq = sequence
    rot = axis_angle_to_matrix(seq.poses.astype(np.float64))
    rel = np.einsum("tjik,tjil->tjkl", rot[:-1], rot[1:])  # R_t^T R_{t+1}
    step = np.degrees(np.linalg.norm(matrix_to_axis_angle(rel), axis=-1))
    assert step.max() < 25.0  # at 30 fps: < 750 deg/s, fast (dance) but no jumps
    root = axis_angle_to_matrix(seq.Rh.astype(np.float64))
    root_step = np.degrees(
        np.linalg.norm(matrix_to_axis_angle(np.einsum("tik,til->tkl", root[:-1], root[1:])), axis=-1)
    )
    assert root_step.max() < 10.0
    assert np.linalg.norm(np.diff(seq.Th, axis=0), axis=1).max() < 0.1


def test_training_range_shows_every_side_of_the_subject(sequence):
    name, seq = sequence
    facing = axis_angle_to_matrix(seq.Rh.astype(np.float64)) @ np.array([0.0, 0.0, 1.0])
    yaw = np.unwrap(np.arctan2(facing[:, 0], -facing[:, 1]))
    if name == "approach":  # walks its line, half a turn at each end: a revolution per cycle (~8 s)
        long = make_motion(name, 300, FPS, np.random.default_rng(7), 300)
        facing = axis_angle_to_matrix(long.Rh.astype(np.float64)) @ np.array([0.0, 0.0, 1.0])
        yaw = np.unwrap(np.arctan2(facing[:, 0], -facing[:, 1]))
        assert abs(yaw[-1] - yaw[0]) > np.radians(340)
        return
    assert abs(yaw[NOVEL_START - 1] - yaw[0]) > np.radians(340)


def test_held_out_tail_uses_new_parameters():
    seq = make_motion("mixed", FRAMES, FPS, np.random.default_rng(1), NOVEL_START)
    assert [s.name for s in seq.segments] == ["turn", "walk", "wave", "dance", "walk+wave"]
    assert seq.segments[-1].start == NOVEL_START
    single = make_motion("wave", FRAMES, FPS, np.random.default_rng(1), NOVEL_START)
    assert [(s.name, s.start) for s in single.segments] == [("wave", 0), ("wave", NOVEL_START)]


def test_same_seed_same_motion_other_seed_other_motion():
    a = make_motion("dance", 90, FPS, np.random.default_rng(3), 60)
    b = make_motion("dance", 90, FPS, np.random.default_rng(3), 60)
    c = make_motion("dance", 90, FPS, np.random.default_rng(4), 60)
    for field in ("poses", "Rh", "Th"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert np.abs(a.poses - c.poses).max() > 0.1


def test_unknown_motion_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown motion 'moonwalk'"):
        make_motion("moonwalk", 10, FPS, np.random.default_rng(0))


def test_rotation_helpers_agree_with_scipy():
    rng = np.random.default_rng(0)
    rotvec = rng.normal(size=(200, 3))
    rotvec[:10] *= np.pi / np.linalg.norm(rotvec[:10], axis=1, keepdims=True)  # angle exactly pi
    rotvec[10:20] *= 1e-9
    expected = Rotation.from_rotvec(rotvec).as_matrix()
    np.testing.assert_allclose(axis_angle_to_matrix(rotvec), expected, atol=1e-12)
    back = axis_angle_to_matrix(matrix_to_axis_angle(expected))
    np.testing.assert_allclose(back, expected, atol=1e-9)
    euler = rng.uniform(-1.2, 1.2, size=(50, 3))
    scipy_zyx = Rotation.from_euler("ZYX", euler[:, ::-1]).as_matrix()
    np.testing.assert_allclose(euler_zyx_to_matrix(euler), scipy_zyx, atol=1e-12)


def _joint_speeds_deg_s(seq) -> np.ndarray:
    """(N-1, 24) angular speed of every joint's local rotation, degrees per second."""
    rot = axis_angle_to_matrix(seq.poses.astype(np.float64))
    rel = np.einsum("tjik,tjil->tjkl", rot[:-1], rot[1:])
    return np.degrees(np.linalg.norm(matrix_to_axis_angle(rel), axis=-1)) * seq.fps


def test_still_subject_breathes_and_turns_its_head_and_nothing_moves_fast():
    still = make_motion("still", FRAMES, FPS, np.random.default_rng(7), NOVEL_START)
    dance = make_motion("dance", FRAMES, FPS, np.random.default_rng(7), NOVEL_START)
    still_speed, dance_speed = _joint_speeds_deg_s(still), _joint_speeds_deg_s(dance)
    assert still_speed.max() < 30.0  # slow head turns at most; a dance swings elbows at ~500 deg/s
    assert np.median(dance_speed.max(axis=1)) > 10 * still_speed.max()
    neck_turn = np.ptp(still.euler_deg[:, JOINT_INDEX["neck"], 1])
    assert 10.0 < neck_turn < 2 * 15.0 + 1e-9  # small head turns
    arms = [JOINT_INDEX[f"{s}_{j}"] for s in ("left", "right") for j in ("shoulder", "elbow", "wrist")]
    assert still_speed[:, arms].max() < 1e-6  # the arms hang still


def test_still_subject_breathes_at_a_resting_rate():
    """The chest's dominant frequency (FFT of the spine's extension over 40 s) is 12-18 breaths a minute."""
    seq = make_motion("still", 1200, FPS, np.random.default_rng(5))
    chest = seq.euler_deg[:, JOINT_INDEX["spine2"], 0]
    spectrum = np.abs(np.fft.rfft(chest - chest.mean()))
    freqs = np.fft.rfftfreq(chest.size, 1 / FPS)
    assert 0.2 - 0.03 <= freqs[spectrum.argmax()] <= 0.3 + 0.03
    assert 0.5 < np.ptp(chest) < 3.0  # about a degree of extension, not a bow


def _root_yaw_deg(seq) -> np.ndarray:
    """(N,) unwrapped turn of the body's forward direction about the world's vertical (scipy)."""
    forward = Rotation.from_rotvec(seq.Rh.astype(np.float64)).apply(np.array([0.0, 0.0, 1.0]))  # SMPL front
    return np.degrees(np.unwrap(np.arctan2(forward[:, 1], forward[:, 0])))


def test_the_still_motion_is_a_turntable_unless_its_facing_is_held():
    """``still`` turns a full revolution over the training frames (the coverage rule); with
    ``train_yaw_deg=0`` (the trade-off study's ``still_standing``) it stands facing the camera."""
    turning = make_motion("still", FRAMES, FPS, np.random.default_rng(7), NOVEL_START)
    standing = make_motion("still", FRAMES, FPS, np.random.default_rng(7), NOVEL_START, train_yaw_deg=0.0)
    assert abs(np.ptp(_root_yaw_deg(turning)[:NOVEL_START])) >= 360.0 - 1.0
    assert np.ptp(_root_yaw_deg(standing)[:NOVEL_START]) < 2.0  # the weight shift's wobble only
    np.testing.assert_allclose(standing.poses, turning.poses)  # the same breathing and head turns
