"""The per-frame colour correction (stg_node.avatar.exposure) against a known exposure and WB jitter."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from avatar_helpers import small_config

from stg_node.avatar.data_spec import DataSpec
from stg_node.avatar.exposure import ExposureCorrection, log_gain_error
from stg_node.avatar.frames import TrainFrame
from stg_node.avatar.trainer import Trainer


def test_the_sparse_adam_moves_only_the_frame_drawn_and_keeps_black_black():
    correction = ExposureCorrection(lr=0.1, weight=0.0, start_iter=0)
    for frame in (3, 4, 5):
        correction.add(frame)
    rgb = torch.full((4, 4, 3), 0.5)
    rgb[0] = 0.0
    out = correction.apply(rgb, 4, iteration=10)
    target = torch.full((4, 4, 3), 0.5) * torch.tensor([1.2, 1.0, 0.8])
    target[0] = 0.0
    ((out - target) ** 2).mean().backward()
    correction.step()
    gains = correction.gains_of()
    assert np.allclose(gains[3], 1.0) and np.allclose(gains[5], 1.0)
    assert gains[4][0] > 1.0 and gains[4][2] < 1.0  # towards the target's tint
    assert correction.apply(rgb, 4, iteration=11)[0].abs().max() == 0.0  # black stays black
    before = correction.gains_of()[4].copy()
    correction.step()  # nothing active: nothing moves (no stale momentum)
    assert np.array_equal(correction.gains_of()[4], before)


def test_before_the_start_the_gains_are_not_learnt():
    correction = ExposureCorrection(lr=0.1, weight=1.0, start_iter=100)
    correction.add(0)
    correction.apply(torch.ones(2, 2, 3), 0, iteration=5)
    assert correction.penalty() is None
    correction.step()
    assert np.allclose(correction.gains_of()[0], 1.0)


def test_a_configuration_written_before_the_correction_existed_loads_without_it():
    from stg_node.avatar.config import TrainConfig
    from stg_node.avatar.presets import preset

    today = preset("fast")
    assert today.lr_exposure > 0
    older = today.to_dict()
    del older["lr_exposure"]
    assert TrainConfig.from_dict(older).lr_exposure == 0.0  # as it trained: no colour correction
    assert TrainConfig.from_dict(today.to_dict()) == today


def test_state_round_trips():
    correction = ExposureCorrection(lr=0.1, weight=0.0, start_iter=0)
    for frame in (7, 2):
        correction.add(frame)
    correction.apply(torch.ones(2, 2, 3), 2, iteration=1).sum().backward()
    correction.step()
    again = ExposureCorrection(lr=0.1, weight=0.0, start_iter=0)
    again.load_state_arrays(correction.state_arrays())
    assert again.slots == correction.slots
    assert torch.equal(again.gains, correction.gains) and torch.equal(again.steps, correction.steps)


@pytest.fixture(scope="module")
def jittered(tmp_path_factory):
    from stg_node.data.synth.generate import SynthConfig, generate

    out = tmp_path_factory.mktemp("exposure") / "jitter"
    generate(
        SynthConfig(out=out, num_frames=12, size=96, num_novel_views=1, view_every=4, supersample=1,
                    motion="turn", exposure_jitter=0.25),
        progress=False,
    )  # fmt: skip
    return out


def test_training_finds_the_jitter_it_was_given(jittered):
    """On a subject whose training frames were multiplied by known per-channel gains (std 0.28 in log),
    the learnt gains follow them: the error is a fraction of the jitter, and far below learning none."""
    meta = json.loads((jittered / "synth.json").read_text())
    truth = {
        i: np.asarray(g) for i, g in enumerate(meta["filming"]["exposure_gains"][: meta["num_train_frames"]])
    }
    frames = [TrainFrame.from_sample(s) for s in DataSpec(str(jittered), "synthetic", size=96).open("train")]
    config = small_config(iterations=300, lr_exposure=0.02, **{"loss.warmup_iters": 60})
    trainer = Trainer(config, seed=0)
    trainer.add_frames(frames)
    for _ in range(config.iterations):
        trainer.step()
    learnt = trainer.exposure.gains_of()
    none = {f: np.ones(3) for f in truth}
    error, baseline = log_gain_error(learnt, truth), log_gain_error(none, truth)
    a = np.log(np.stack([learnt[f] for f in sorted(truth)]))
    b = np.log(np.stack([truth[f] for f in sorted(truth)]))
    correlation = np.corrcoef((a - a.mean(0)).ravel(), (b - b.mean(0)).ravel())[0, 1]
    assert baseline > 0.15
    assert correlation > 0.8 and error < 0.6 * baseline, (error, baseline, correlation)
