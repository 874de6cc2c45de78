"""The colour MLP in turns during training (``color_every``, issue 24): which rows a step
evaluates, what the others carry, the gradient the evaluated rows pass on, when the carried
colours are dropped, and a model trained so scoring like one trained with every row every step."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from avatar_helpers import small_config, trained_held_out_psnr

from stg_node.avatar.color_cache import TrainingColorTurns
from stg_node.avatar.config import TrainConfig
from stg_node.avatar.frames import TrainFrame
from stg_node.avatar.trainer import Trainer


def _network(weights: torch.Tensor, inputs: torch.Tensor):
    """A stand-in colour network: row i's colour is sigmoid(inputs[i] @ weights)."""

    def evaluate(sel):
        x = inputs if sel is None else inputs[sel]
        return torch.sigmoid(x @ weights)

    return evaluate


def test_a_step_evaluates_its_turn_of_the_rows_and_carries_the_others():
    torch.manual_seed(0)
    rows_total, every = 10, 3
    inputs = torch.randn(rows_total, 4, dtype=torch.float64)
    weights = torch.randn(4, 3, dtype=torch.float64, requires_grad=True)
    turns = TrainingColorTurns(every)
    key = ("model", 0, 0)
    # first call: every row, with its gradient as is
    first = turns.colors(_network(weights, inputs), None, rows_total, 0, key)
    assert turns.evaluated == rows_total
    torch.testing.assert_close(first, torch.sigmoid(inputs @ weights), rtol=0, atol=0)
    expected = torch.sigmoid(inputs @ weights).detach().clone()
    # the network changes; step 4 (turn 1) renders the rows 2, 4, 5, 7 (a culled subset)
    with torch.no_grad():
        weights.add_(0.5)
    rendered = torch.tensor([2, 4, 5, 7])
    out = turns.colors(_network(weights, inputs[rendered]), rendered, rows_total, 4, key)
    due = rendered % every == 4 % every  # rows 4 and 7
    assert turns.evaluated == int(due.sum()) == 2
    fresh = torch.sigmoid(inputs[rendered] @ weights)
    torch.testing.assert_close(out[due], fresh[due], rtol=0, atol=0)
    torch.testing.assert_close(out[~due], expected[rendered][~due], rtol=0, atol=0)
    # the gradient: every times the evaluated rows' own, none from the carried rows
    upstream = torch.randn_like(out)
    (out * upstream).sum().backward()
    reference = weights.detach().clone().requires_grad_(True)
    (torch.sigmoid(inputs[rendered][due] @ reference) * upstream[due]).sum().backward()
    torch.testing.assert_close(weights.grad, every * reference.grad, rtol=1e-12, atol=1e-12)
    # the evaluated rows' new colours are carried from now on
    with torch.no_grad():
        later = turns.colors(_network(weights, inputs), None, rows_total, 6, key)  # turn 0: rows 0, 3, 6, 9
    torch.testing.assert_close(later[[4, 7]], fresh[due].detach(), rtol=0, atol=0)


def test_the_refreshed_rows_node_is_index_put_behind_a_scaled_gradient_to_the_bit():
    """color_cache._Refreshed against the composition it replaced: an out-of-place index_put of
    the fresh rows whose gradient is scaled (x + (s - 1)(x - x.detach()) for the scaling)."""
    from stg_node.avatar.color_cache import _Refreshed

    gen = torch.Generator().manual_seed(2)
    carried = torch.rand(500, 3, generator=gen)
    sel = torch.randperm(500, generator=gen)[:170]
    x = torch.rand(170, 3, generator=gen)
    g = torch.randn(500, 3, generator=gen)
    got_x, want_x = x.clone().requires_grad_(True), x.clone().requires_grad_(True)
    got = _Refreshed.apply(carried, sel, got_x, 3.0)
    want = carried.index_put((sel,), want_x + 2.0 * (want_x - want_x.detach()))
    assert torch.equal(got, want)
    (got * g).sum().backward()
    (want * g).sum().backward()
    assert torch.equal(got_x.grad, want_x.grad)
    assert not torch.equal(got_x.grad, g[sel])  # the scale is there


def test_changed_rows_or_a_reset_start_a_full_evaluation_and_every_1_is_the_exact_network():
    inputs = torch.randn(8, 4)
    weights = torch.randn(4, 3)
    turns = TrainingColorTurns(2)
    turns.colors(_network(weights, inputs), None, 8, 0, ("m", 0, 0))
    turns.colors(_network(weights, inputs), None, 8, 1, ("m", 0, 0))
    assert turns.evaluated == 4
    turns.colors(_network(weights, inputs), None, 8, 2, ("m", 0, 1))  # the table's rows changed
    assert turns.evaluated == 8
    turns.colors(_network(weights, inputs[:6]), None, 6, 3, ("m", 0, 1))  # fewer rows
    assert turns.evaluated == 6
    turns.reset()
    turns.colors(_network(weights, inputs[:6]), None, 6, 4, ("m", 0, 1))
    assert turns.evaluated == 6
    exact = TrainingColorTurns(1)
    for it in range(3):
        out = exact.colors(_network(weights, inputs), None, 8, it, ("m", 0, 0))
        assert exact.evaluated == 8
        torch.testing.assert_close(out, torch.sigmoid(inputs @ weights), rtol=0, atol=0)
    with pytest.raises(ValueError, match="color_every must be >= 1"):
        TrainingColorTurns(0)


def test_the_trainer_evaluates_a_third_of_the_rows_by_default_on_a_cpu(tiny_frames):
    """Today's default (3): after the first step a step evaluates the colour of about a third of
    the rows (every row again when densification changed the table), and the features learn at
    sqrt(3) x lr_color."""
    assert TrainConfig().color_every == 3
    trainer = Trainer(small_config(iterations=30), seed=0)
    trainer.add_frames(tiny_frames)
    counts = []
    for _ in range(12):
        trainer.step()
        counts.append((trainer.color_turns.evaluated, trainer.model.table.num))
    assert counts[0][0] == counts[0][1]
    thirds = [e / n for e, n in counts[1:]]
    assert sum(0.25 < share < 0.42 for share in thirds) >= 9, counts
    base = trainer.optimizer.base_lrs
    assert base["features"] == pytest.approx(3**0.5 * trainer.config.lr_color, rel=1e-12)
    assert base["sh"] == trainer.config.lr_color
    with pytest.raises(ValueError, match="color_every must be >= 1"):
        small_config(color_every=0).validate()


def test_a_second_training_camera_ends_the_turns_and_their_rate(tiny_frames):
    """From a rig (issue 25) every row is evaluated every step, from the first camera on or when a
    second camera arrives mid-run (a live rig), and the features' rate drops back to lr_color."""
    second = [
        TrainFrame(f.index, f.time, f.image, f.mask, dataclasses.replace(f.camera, name="B"), f.smpl)
        for f in tiny_frames
    ]
    rig = Trainer(small_config(iterations=30), seed=0)
    rig.add_frames([f for pair in zip(tiny_frames, second, strict=True) for f in pair])
    assert rig.color_turns is None
    assert rig.optimizer.base_lrs["features"] == rig.config.lr_color
    live = Trainer(small_config(iterations=30), seed=0)
    live.add_frames(tiny_frames)
    for _ in range(3):
        live.step()
    assert live.color_turns is not None and live.color_turns.evaluated < live.model.table.num
    live.add_frames(second[:1])
    assert live.color_turns is None
    live.step()
    assert live.optimizer.lr("features") <= live.config.lr_color
    assert live.optimizer.base_lrs["features"] == live.config.lr_color


def test_a_config_stored_before_the_setting_reads_it_as_every_row():
    stored = TrainConfig().to_dict()
    del stored["color_every"]
    assert TrainConfig.from_dict(stored).color_every == 1


def test_training_with_the_colour_in_turns_scores_like_every_row_every_step(tiny_frames, tiny_synth):
    """Same seed and schedule (200 steps, densification, pose refinement): the model trained with
    the colour MLP on every 3rd row per step scores within 0.1 dB of the one trained with every
    row, on held-out views."""
    scores = {
        every: trained_held_out_psnr(tiny_frames, tiny_synth, small_config(iterations=200, color_every=every))
        for every in (1, 3)
    }
    assert scores[1] > 18.0
    assert abs(scores[3] - scores[1]) <= 0.1, scores
