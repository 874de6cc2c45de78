"""stg-synth's filming conditions: the rig's distance and field of view, the training camera's exposure
drift, and the motion that walks towards the camera and away."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from stg_node.data.synth import SynthConfig, generate
from stg_node.data.synth.cameras import make_rig
from stg_node.data.synth.exposure import apply_gain, jitter_gains
from stg_node.data.synth.motions import make_motion


def test_the_rig_takes_a_distance_and_a_field_of_view():
    rig = make_rig(200, 3, np.random.default_rng(0), distance=6.0, fov_deg=40.0)
    for k, cam in enumerate(rig):
        eye = -cam.R.T @ cam.t
        ground = math.hypot(eye[0], eye[1])
        assert ground == pytest.approx(6.0, abs=1e-9 if k == 0 else 0.31)
        assert 2 * math.degrees(math.atan(100 / cam.K[0, 0])) == pytest.approx(40.0)


def test_exposure_gains_drift_smoothly_about_one():
    gains = jitter_gains(400, 300, 0.2, 30.0, np.random.default_rng(1))
    log = np.log(gains[:300])
    np.testing.assert_allclose(log.mean(axis=0), 0.0, atol=1e-9)  # the mean colour is the true one
    assert np.all(gains[300:] == 1.0)  # held-out frames are steady
    # exposure (shared) and white balance (per channel): std sqrt(0.2^2 + 0.1^2) per channel
    np.testing.assert_allclose(log.std(axis=0), math.hypot(0.2, 0.1), rtol=0.25)
    assert np.abs(np.diff(log, axis=0)).mean() < 0.25 * log.std()  # smooth, not frame-to-frame noise
    assert np.all(jitter_gains(10, 8, 0.0, 30.0, np.random.default_rng(0)) == 1.0)


def test_apply_gain_scales_rounds_and_clips():
    image = np.array([[[100, 200, 250]]], np.uint8)
    np.testing.assert_array_equal(apply_gain(image, [1.5, 0.5, 1.1]), [[[150, 100, 255]]])


def test_the_approach_motion_walks_two_metres_towards_the_camera_and_back():
    motion = make_motion("approach", 300, 30.0, np.random.default_rng(3), 300)
    # The training camera is on -y: the distance changes along y.
    y = motion.Th[:, 1]
    assert y.min() < -0.9 and y.max() > 0.9
    step = np.linalg.norm(np.diff(motion.Th[:, :2], axis=0), axis=1) * 30.0
    assert step.max() < 1.2  # walking speed, no jumps


def test_a_jittered_subject_differs_from_the_steady_one_only_by_the_gains(tmp_path):
    common = dict(num_frames=4, size=48, num_novel_views=1, view_every=2, supersample=1, motion="turn")
    steady = generate(SynthConfig(out=tmp_path / "steady", **common), progress=False)
    jitter = generate(SynthConfig(out=tmp_path / "jitter", exposure_jitter=0.3, **common), progress=False)
    from stg_node.data.io import read_image

    meta = json.loads((jitter.out / "synth.json").read_text())
    gains = np.asarray(meta["filming"]["exposure_gains"])
    assert "filming" not in json.loads((steady.out / "synth.json").read_text())
    n_train = meta["num_train_frames"]
    for frame in range(4):
        a = read_image(steady.out / "Camera_B1" / f"{frame:06d}.png")
        b = read_image(jitter.out / "Camera_B1" / f"{frame:06d}.png")
        np.testing.assert_array_equal(b, apply_gain(a, gains[frame]))
        if frame < n_train:
            assert not np.array_equal(a, b)
    for name in ("Camera_B2/000000.png", "mask/Camera_B1/000001.png"):  # held-out views, masks: untouched
        assert (steady.out / name).read_bytes() == (jitter.out / name).read_bytes()
