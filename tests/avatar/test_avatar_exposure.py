"""The per-frame colour correction (stg_node.avatar.exposure) against a known exposure and WB jitter."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from avatar_helpers import small_config

from stg_node.avatar.data_spec import DataSpec
from stg_node.avatar.exposure import FOOTAGE_RATE, ExposureCorrection, for_footage, log_gain_error
from stg_node.avatar.frames import TrainFrame
from stg_node.avatar.trainer import Trainer


def _frames_pair(gains_a, gains_b):
    """A textured render and two images of it under known per-channel gains (clipped as a camera clips)."""
    rng = np.random.default_rng(0)
    rgb = torch.from_numpy(rng.uniform(0.05, 0.95, (24, 24, 3))).float()
    rgb[:4] = 0.0  # black background
    region = torch.ones(24, 24, dtype=torch.bool)
    images = [(rgb * torch.tensor(g, dtype=torch.float32)).clamp(max=1.0) for g in (gains_a, gains_b)]
    images = [(img * 255).round() / 255 for img in images]  # 8-bit, as the data
    return rgb, region, images


def test_one_draw_finds_the_gains_ratio_and_keeps_black_black():
    truth_a, truth_b = np.array([1.3, 1.0, 0.8]), np.array([0.9, 1.1, 1.25])
    rgb, region, (image_a, image_b) = _frames_pair(truth_a, truth_b)
    correction = ExposureCorrection(rate=0.5, start_iter=0)
    for frame in (3, 4, 5):
        correction.add(frame)
    out_a = correction.apply(rgb, 3, 0, image_a, region)
    correction.apply(rgb, 4, 0, image_b, region)
    gains = correction.gains_of()
    # The gauge: the applied gains are the true ones over their geometric mean (frames 3 and 4 seen).
    mean = np.sqrt(truth_a * truth_b)
    assert np.allclose(gains[3], truth_a / mean, rtol=5e-3)
    assert np.allclose(gains[4], truth_b / mean, rtol=5e-3)
    assert np.allclose(gains[5], 1.0)  # never drawn: no correction
    assert np.allclose(gains[3] / gains[4], truth_a / truth_b, rtol=5e-3)
    assert out_a[:4].abs().max() == 0.0  # black stays black
    assert float(out_a.max()) <= 1.0  # clipped as the camera clips
    assert torch.equal(correction.apply(rgb, 5, 0), rgb)  # a frame never estimated renders as is


def test_saturated_pixels_do_not_bias_the_gain():
    """An image 1.6x brighter clips a third of its pixels; the least-squares gain over all pixels
    would come out low, the one over the unsaturated pixels is the truth."""
    truth = np.array([1.6, 1.6, 1.6])
    rgb, region, (bright, steady) = _frames_pair(truth, np.ones(3))
    assert float((bright >= 1.0).float().mean()) > 0.2
    correction = ExposureCorrection(rate=1.0, start_iter=0)
    correction.add(0)
    correction.add(1)
    correction.apply(rgb, 0, 0, bright, region)
    correction.apply(rgb, 1, 0, steady, region)
    gains = correction.gains_of()
    assert np.allclose(gains[0] / gains[1], truth, rtol=5e-3)


def test_later_draws_move_by_the_rate_and_a_region_too_small_estimates_nothing():
    rgb, region, (image, _) = _frames_pair(np.full(3, 1.2), np.ones(3))
    correction = ExposureCorrection(rate=0.25, start_iter=0)
    correction.add(0)
    correction.add(1)
    correction.apply(rgb, 1, 0, rgb, region)  # frame 1: gain 1 (the anchor's other frame)
    correction.apply(rgb, 0, 0, rgb, region)  # first draw of frame 0: its estimate, 1
    correction.apply(rgb, 0, 1, image, region)  # second: a quarter of the way to 1.2 (in log)
    expected = np.exp(0.25 * np.log(1.2))
    gains = correction.gains_of()
    assert np.allclose(gains[0] / gains[1], expected, rtol=5e-3)
    tiny = torch.zeros_like(region)
    tiny[0, :5] = True
    before = correction.gains_of()[0].copy()
    correction.apply(rgb, 0, 2, image * 0.5, tiny)
    assert np.array_equal(correction.gains_of()[0], before)


def test_before_the_start_the_gains_are_not_learnt():
    correction = ExposureCorrection(rate=0.5, start_iter=100)
    correction.add(0)
    rgb, region, (image, _) = _frames_pair(np.full(3, 1.3), np.ones(3))
    assert torch.equal(correction.apply(rgb, 0, 5, image, region), rgb)
    assert np.allclose(correction.gains_of()[0], 1.0)


def test_a_rate_outside_zero_to_one_is_refused():
    with pytest.raises(ValueError, match="lr_exposure"):
        ExposureCorrection(rate=1.5, start_iter=0)


def test_a_configuration_written_before_the_correction_existed_loads_without_it():
    from stg_node.avatar.config import TrainConfig
    from stg_node.avatar.presets import preset

    today = for_footage(preset("fast"))
    assert today.lr_exposure > 0
    older = today.to_dict()
    del older["lr_exposure"]
    assert TrainConfig.from_dict(older).lr_exposure == 0.0  # as it trained: no colour correction
    assert TrainConfig.from_dict(today.to_dict()) == today


def test_the_correction_is_on_for_footage_and_off_for_fixed_exposure_data():
    from stg_node.avatar.presets import preset
    from stg_node.nodes.avatar_adapter import TrainerAdapter

    for name in ("fast", "balanced", "quality"):
        assert preset(name).lr_exposure == 0.0  # datasets filmed at a fixed exposure
        assert for_footage(preset(name)).lr_exposure == FOOTAGE_RATE
    chosen = preset("fast").replace(lr_exposure=0.2)  # a user's --set is kept
    assert for_footage(chosen).lr_exposure == 0.2
    # the trainer node on a live camera (launch/live_*.yaml: exposure_correction: true)
    assert TrainerAdapter.create(footage=True)._trainer.config.lr_exposure == FOOTAGE_RATE
    assert TrainerAdapter.create(footage=False)._trainer.config.lr_exposure == 0.0


def test_state_round_trips():
    rgb, region, (image_a, image_b) = _frames_pair(np.full(3, 1.2), np.full(3, 0.9))
    correction = ExposureCorrection(rate=0.5, start_iter=0)
    for frame in (7, 2):
        correction.add(frame)
    correction.apply(rgb, 2, 1, image_a, region)
    correction.apply(rgb, 7, 1, image_b, region)
    again = ExposureCorrection(rate=0.5, start_iter=0)
    again.load_state_arrays(correction.state_arrays())
    assert again.slots == correction.slots
    assert torch.equal(again.gains, correction.gains) and torch.equal(again.steps, correction.steps)
    older = dict(correction.state_arrays(), exp_avg=np.zeros((2, 3)), exp_avg_sq=np.zeros((2, 3)))
    again.load_state_arrays(older)  # a checkpoint of the Adam this replaced: its moments are dropped
    assert torch.equal(again.gains, correction.gains)


@pytest.fixture(scope="module")
def jittered(tmp_path_factory):
    from stg_node.data.synth.generate import SynthConfig, generate

    out = tmp_path_factory.mktemp("exposure") / "jitter"
    generate(
        SynthConfig(out=out, num_frames=12, size=96, num_novel_views=1, view_every=4, supersample=1,
                    motion="wave", exposure_jitter=0.25),
        progress=False,
    )  # fmt: skip
    return out


def test_training_finds_the_jitter_it_was_given(jittered):
    """On a subject whose training frames were multiplied by known per-channel gains (std 0.28 in
    log), the gains learnt in training follow them: slope about 1 on the truth, well correlated.
    The subject waves facing the camera: a body that turns shows sides of
    different brightness from frame to frame, which a half-trained avatar has not learnt yet and
    the gains take in part (docs/AVATAR.md). 700 steps: at 300 the correlation sat on its bar
    (0.7990-0.8002 as float rounding moved with the kernels); at 700 it is 0.89 and the slope 0.98."""
    meta = json.loads((jittered / "synth.json").read_text())
    truth = {
        i: np.asarray(g) for i, g in enumerate(meta["filming"]["exposure_gains"][: meta["num_train_frames"]])
    }
    frames = [TrainFrame.from_sample(s) for s in DataSpec(str(jittered), "synthetic", size=96).open("train")]
    config = small_config(iterations=700, exposure_start=30, lr_exposure=FOOTAGE_RATE)
    trainer = Trainer(config, seed=0)
    trainer.add_frames(frames)
    for _ in range(config.iterations):
        trainer.step()
    learnt = trainer.exposure.gains_of()
    none = {f: np.ones(3) for f in truth}
    error, baseline = log_gain_error(learnt, truth), log_gain_error(none, truth)
    a = np.log(np.stack([learnt[f] for f in sorted(truth)]))
    b = np.log(np.stack([truth[f] for f in sorted(truth)]))
    a, b = a - a.mean(0), b - b.mean(0)
    slope = float((a * b).sum() / (b * b).sum())
    correlation = float(np.corrcoef(a.ravel(), b.ravel())[0, 1])
    assert baseline > 0.15
    # The Adam this replaced ended at a slope of 0.22 at mid scale (BENCHMARKS.md); the error left
    # is the tiny avatar's own frame-to-frame error, which the gains take with the drift.
    assert 0.8 < slope < 1.2 and correlation > 0.8, (slope, correlation)
    assert error < 0.8 * baseline, (error, baseline)
