"""The isometry term on every k-th step (``loss.isometry_every``, issue 24): which steps evaluate
it, the weight those steps carry (k times the configured one, 1 = every step as before), the
checkpoint's graph, and a model trained so scoring like one trained with the term on every step."""

from __future__ import annotations

import pytest
import torch
from avatar_helpers import small_config, trained_held_out_psnr

from stg_node.avatar.config import TrainConfig
from stg_node.avatar.trainer import Trainer


def _steps(config, frames, steps: int):
    trainer = Trainer(config, seed=0)
    trainer.add_frames(frames)
    return trainer, [trainer.step() for _ in range(steps)]


@pytest.mark.parametrize("every", [1, 3])
def test_the_isometry_term_comes_every_kth_step_at_k_times_its_weight(tiny_frames, every):
    """k = 3: the term on steps 0, 3, 6, ... only, at 3 x ``loss.isometry``; k = 1: on every step
    at the configured weight (the behaviour before the setting)."""
    config = small_config(iterations=20, **{"loss.isometry_every": every, "loss.adaptive": False})
    _, results = _steps(config, tiny_frames, config.iterations)
    for it, result in enumerate(results):
        assert ("isometry" in result.losses) == (it % every == 0), it
        if it % every == 0:
            assert result.losses["isometry"] > 0, it
            assert result.weights["isometry"] == pytest.approx(every * config.loss.isometry, rel=1e-12)


def test_the_total_loss_carries_the_term_k_times_on_its_steps(tiny_frames):
    """Step 0 (the same model, frame and terms whatever k): the total loss of k = 3 exceeds the one
    of k = 1 by exactly (3 - 1) x weight x the term's value."""
    one = _steps(small_config(**{"loss.isometry_every": 1, "loss.adaptive": False}), tiny_frames, 1)[1][0]
    three = _steps(small_config(**{"loss.isometry_every": 3, "loss.adaptive": False}), tiny_frames, 1)[1][0]
    assert three.losses["isometry"] == one.losses["isometry"] > 0
    extra = 2 * small_config().loss.isometry * one.losses["isometry"]
    assert three.loss - one.loss == pytest.approx(extra, rel=1e-4)


def test_a_checkpoint_keeps_the_graph_only_while_it_is_the_tables():
    """Rows edited after the last step that evaluated the term (densification between two such
    steps) make the graph stale: the checkpoint leaves it out (the resumed run rebuilds it on its
    next evaluation, as the uninterrupted one does) and keeps it again once it is rebuilt."""
    from stg_node.avatar.gaussians import GaussianTable
    from stg_node.avatar.isometry import IsometryGraph
    from stg_node.avatar.optim import TableOptimizer

    table = GaussianTable({"means": torch.rand(40, 3, generator=torch.Generator().manual_seed(0))})
    opt = TableOptimizer(table, {"means": 0.1}, {})
    graph = IsometryGraph(k=3)
    points = table["means"].detach()
    graph.loss(table, points, points, None)
    assert torch.equal(graph.state_arrays(table)["neighbours"], graph.neighbours.float())
    opt.keep(torch.arange(40) != 0)  # one row pruned: the graph is the old rows'
    opt.append({"means": torch.rand(1, 3)})  # and one appended: as many rows as before
    assert graph.state_arrays(table) == {}
    assert graph.state_arrays() != {}  # without a table: as before (no check)
    points = table["means"].detach()
    graph.loss(table, points, points, None)  # the next evaluation rebuilds it
    assert torch.equal(graph.state_arrays(table)["neighbours"], graph.neighbours.float())


def test_training_with_the_isometry_term_every_4th_step_scores_like_every_step(tiny_frames, tiny_synth):
    """Same seed and schedule (200 steps, densification, pose refinement): the model trained with
    the isometry term on every 4th step scores within 0.1 dB of the one trained with it on every
    step, on held-out views."""
    scores = {
        every: trained_held_out_psnr(
            tiny_frames, tiny_synth, small_config(iterations=200, **{"loss.isometry_every": every})
        )
        for every in (1, 4)
    }
    assert scores[1] > 18.0
    assert abs(scores[4] - scores[1]) <= 0.1, scores


def test_a_config_stored_before_the_setting_reads_it_as_every_step_and_bad_values_are_refused():
    stored = TrainConfig().to_dict()
    assert stored["loss"]["isometry_every"] == 4  # today's default
    del stored["loss"]["isometry_every"]
    assert TrainConfig.from_dict(stored).loss.isometry_every == 1  # what that run trained with
    with pytest.raises(ValueError, match="loss.isometry_every must be >= 1"):
        small_config(**{"loss.isometry_every": 0}).validate()
