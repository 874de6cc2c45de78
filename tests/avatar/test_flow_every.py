"""The flow term on every k-th step (``loss.flow_every``, issue 24): which steps render the
Gaussians' motion, the weight those steps carry, and a model trained so scoring like one trained
with the flow term on every step."""

from __future__ import annotations

import pytest
from avatar_helpers import small_config, trained_held_out_psnr

from stg_node.avatar.config import TrainConfig
from stg_node.avatar.trainer import Trainer


def test_the_flow_term_comes_every_kth_step_and_on_every_flow_round(tiny_frames):
    """k = 3 with flow rounds every 7 steps from step 20: the term (and its motion channels) on
    steps 0, 3, 6, ... and on 20, 27, 34, ..., on no other; at k times the configured weight."""
    config = small_config(
        iterations=60,
        **{
            "loss.flow_every": 3,
            "loss.adaptive": False,
            "densify.start_iter": 20,
            "densify.flow_interval": 7,
        },
    )
    trainer = Trainer(config, seed=0)
    trainer.add_frames(tiny_frames)
    has_next = {f.frame.index: f.next_smpl is not None for f in trainer.store.frames}
    seen = 0
    for it in range(config.iterations):
        result = trainer.step()
        flow_round = trainer.densifier.active(it) and (it - 20) % 7 == 0
        wanted = (it % 3 == 0 or flow_round) and has_next[result.frame]
        assert ("flow" in result.losses) == wanted, it
        if wanted:
            seen += 1
            assert abs(result.weights["flow"] - 3 * config.loss.flow) < 1e-12
    assert seen >= 15


def test_training_with_the_flow_term_every_4th_step_scores_like_every_step(tiny_frames, tiny_synth):
    """Same seed and schedule (200 steps, densification with flow rounds, pose refinement): the
    model trained with the flow term on every 4th step scores within 0.1 dB of the one trained
    with it on every step, on held-out views."""
    scores = {
        every: trained_held_out_psnr(
            tiny_frames, tiny_synth, small_config(iterations=200, **{"loss.flow_every": every})
        )
        for every in (1, 4)
    }
    assert scores[1] > 18.0
    assert abs(scores[4] - scores[1]) <= 0.1, scores


def test_a_config_stored_before_the_setting_reads_it_as_every_step_and_bad_values_are_refused():
    stored = TrainConfig().to_dict()
    assert stored["loss"]["flow_every"] == 4  # today's default
    del stored["loss"]["flow_every"]
    assert TrainConfig.from_dict(stored).loss.flow_every == 1  # what that run trained with
    with pytest.raises(ValueError, match="loss.flow_every must be >= 1"):
        small_config(**{"loss.flow_every": 0}).validate()
