"""Garment dynamics: zero at rest, growing with limb velocity, matching the oscillator closed form."""

from __future__ import annotations

import numpy as np
import pytest

from stg_node.data.synth.garment import GarmentParams, garment_regions, simulate_garment
from stg_node.data.synth.joint_limits import JOINT_INDEX

FPS = 30.0
LINEAR = GarmentParams(max_offset_m=10.0, ripple=0.0)  # no soft clamp in play: the linear model


def _swinging_arm(freq_hz: float, amplitude_rad: float, seconds: float = 6.0) -> np.ndarray:
    """(T, 5, 3): points along an arm swinging about a shoulder at the origin."""
    t = np.arange(int(seconds * FPS)) / FPS
    angle = amplitude_rad * np.sin(2 * np.pi * freq_hz * t)
    radii = np.linspace(0.1, 0.3, 5)
    x = radii[None, :] * np.sin(angle)[:, None]
    y = -radii[None, :] * np.cos(angle)[:, None]
    return np.stack([x, y, np.zeros_like(x)], axis=-1)


def test_zero_offset_for_a_body_at_rest():
    rng = np.random.default_rng(0)
    pose = rng.normal(size=(1, 50, 3))
    trajectory = np.repeat(pose, 40, axis=0)
    offsets = simulate_garment(trajectory, np.ones(50), FPS)
    assert np.count_nonzero(offsets) == 0


def test_deformation_grows_with_limb_velocity():
    rms = []
    for freq in (0.25, 0.5, 1.0, 1.5):
        offsets = simulate_garment(_swinging_arm(freq, 0.6), np.ones(5), FPS)
        rms.append(float(np.sqrt((offsets[60:] ** 2).sum(-1).mean())))
    assert all(later > earlier * 1.3 for earlier, later in zip(rms, rms[1:], strict=False)), rms
    assert rms[0] > 0


def test_steady_velocity_gives_the_drag_trailing_offset():
    params = LINEAR
    velocity = np.array([0.8, 0.0, -0.3])
    t = np.arange(150) / FPS
    trajectory = (t[:, None] * velocity)[:, None, :]
    offsets = simulate_garment(trajectory, np.ones(1), FPS, params)
    omega = 2 * np.pi * params.natural_freq_hz
    expected = -params.drag_per_s * velocity / omega**2  # d'' = d' = 0: w^2 d = -c v
    np.testing.assert_allclose(offsets[-1, 0], expected, rtol=1e-3, atol=1e-6)


def test_sinusoidal_drive_matches_the_oscillator_transfer_function():
    params = LINEAR
    amplitude, freq = 0.05, 1.1
    t = np.arange(int(8 * FPS)) / FPS
    trajectory = np.zeros((len(t), 1, 3))
    trajectory[:, 0, 0] = amplitude * np.sin(2 * np.pi * freq * t)
    offsets = simulate_garment(trajectory, np.ones(1), FPS, params)[:, 0, 0]
    w0 = 2 * np.pi * params.natural_freq_hz
    w = 2 * np.pi * freq
    c = params.drag_per_s
    # d'' + (2 zeta w0 + c) d' + w0^2 d = -(x'' + c x'), x = A sin(w t)  =>  d = Im(D e^{iwt})
    response = amplitude * (w**2 - 1j * c * w) / (w0**2 - w**2 + 1j * (2 * params.damping_ratio * w0 + c) * w)
    expected = np.imag(response * np.exp(1j * w * t))
    settled = t > 4.0
    error = np.abs(offsets[settled] - expected[settled]).max()
    assert error < 0.02 * abs(response), (error, abs(response))


def test_weight_and_soft_clamp_bound_the_offset():
    tip = _swinging_arm(3.0, 1.2)[:, 4:5]
    trajectory = np.repeat(tip, 5, axis=1)  # five copies of the arm tip, weighted differently
    params = GarmentParams(max_offset_m=0.02, ripple=0.0)
    weight = np.array([0.0, 0.25, 0.5, 1.0, 1.0])
    offsets = simulate_garment(trajectory, weight, FPS, params)
    length = np.linalg.norm(offsets, axis=-1)
    assert np.count_nonzero(offsets[:, 0]) == 0
    assert length.max() <= 0.02 + 1e-7
    assert length[:, 3].max() > 0.015  # fast swing: saturates near the clamp
    np.testing.assert_allclose(length[:, 1], 0.25 * length[:, 3], rtol=1e-5, atol=1e-9)


def test_bad_trajectory_is_rejected_with_a_clear_error():
    bad = np.zeros((5, 2, 3))
    bad[2, 1, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        simulate_garment(bad, np.ones(2), FPS)
    with pytest.raises(ValueError, match="weight"):
        simulate_garment(np.zeros((5, 2, 3)), np.ones(3), FPS)


def _toy_rest_body():
    """A point cloud body in SMPL rest axes: a vertical torso column and two horizontal arms."""
    joints = np.zeros((24, 3))
    joints[JOINT_INDEX["pelvis"]] = [0.0, -0.22, 0.0]
    joints[JOINT_INDEX["spine1"]] = [0.0, -0.1, 0.0]
    joints[JOINT_INDEX["spine3"]] = [0.0, 0.1, 0.0]
    joints[JOINT_INDEX["left_hip"]] = [0.1, -0.3, 0.0]
    joints[JOINT_INDEX["right_hip"]] = [-0.1, -0.3, 0.0]
    joints[JOINT_INDEX["left_shoulder"]] = [0.2, 0.23, 0.0]
    joints[JOINT_INDEX["right_shoulder"]] = [-0.2, 0.23, 0.0]
    joints[JOINT_INDEX["left_elbow"]] = [0.45, 0.23, 0.0]
    joints[JOINT_INDEX["right_elbow"]] = [-0.45, 0.23, 0.0]
    torso = np.stack([np.full(60, 0.12), np.linspace(0.2, -0.4, 60), np.zeros(60)], axis=1)
    arm = np.stack([np.linspace(0.2, 0.7, 50), np.full(50, 0.28), np.zeros(50)], axis=1)
    arm_r = arm * [-1, 1, 1]
    return np.concatenate([torso, arm, arm_r]), joints


def test_regions_are_attached_at_chest_and_shoulders_and_free_at_hem_and_sleeve_end():
    vertices, joints = _toy_rest_body()
    params = GarmentParams()
    regions = garment_regions(vertices, joints, params)
    torso_y = vertices[:60, 1]
    hem_y = -0.1 - params.hem_below_joint_m
    torso_w = regions.weight[:60]
    assert torso_w[torso_y >= 0.1].max() == 0.0  # above the attachment (chest): no cloth motion
    assert torso_w[np.argmin(np.abs(torso_y - hem_y))] > 0.95  # free at the hem line
    assert torso_w[torso_y < hem_y - params.fade_m - 1e-6].max() == 0.0  # skin below the fade
    arm_x = vertices[60:110, 0]
    arm_w = regions.weight[60:110]
    sleeve_end = 0.2 + params.sleeve_fraction * 0.25
    assert arm_w[arm_x <= 0.2].max() == 0.0
    assert arm_w[np.argmin(np.abs(arm_x - sleeve_end))] > 0.95
    assert arm_w[arm_x > sleeve_end + params.fade_m + 1e-6].max() == 0.0
    np.testing.assert_allclose(regions.weight[110:], arm_w)  # the sleeves mirror
    assert regions.hem[:60].any() and regions.sleeves[60:].any() and not regions.sleeves[:60].any()
