"""Surface no training view shows keeps a coarse cover (densify.unseen_cell_m, issue 22): one Gaussian per
cube of the canonical space where no row was ever the surface seen; the surface seen is left alone."""

from __future__ import annotations

import math

import pytest
import torch
from avatar_helpers import density_step_inputs, small_config

from stg_node.avatar.trainer import Trainer

CELL = 0.1
AFTER = 5


def _one_density_step(tiny_frames, monkeypatch, cell_m: float):
    """A density step on a hand-made table: nothing clones, splits, prunes or re-samples but the rule.

    Every row sits alone in its own cube 1 m apart and was seen, except: rows 0-2 share a cube, were
    never seen over 6 steps and have opacities 0.2, 0.6, 0.4; rows 3-4 share another
    cube, never seen (opacities 0.5, 0.5); row 5 is in rows 0-2's cube but was seen once; row 6 is in
    rows 3-4's cube, never seen, but has existed for only 2 steps (too young to judge).
    """
    config = small_config(
        **{
            "densify.start_iter": 4,
            "densify.interval": 8,
            "densify.gate_start_iter": 100,
            "densify.prune_opacity": 0.0,
            "densify.prune_score": 0.0,
            "densify.prune_scale_m": 1e9,
            "densify.resample_fraction": 0.0,
            "densify.grad_threshold": 1e9,
            "densify.flow_guided": False,
            "densify.unseen_cell_m": cell_m,
            "densify.unseen_after_views": AFTER,
        }
    )
    trainer = Trainer(config, seed=0)
    trainer.add_frames(tiny_frames)
    trainer.step()
    model, state, strategy = trainer.model, trainer.densify_state, trainer.densifier
    table = model.table
    n = table.num
    means = torch.stack([torch.arange(n, dtype=torch.float32) + 10.0, torch.zeros(n), torch.zeros(n)], dim=1)
    cube_a, cube_b = torch.tensor([0.025, 0.025, 0.025]), torch.tensor([0.225, 0.025, 0.025])
    for row, offset in ((0, 0.0), (1, 0.01), (2, 0.02), (5, 0.03)):
        means[row] = cube_a + offset
    for row, offset in ((3, 0.0), (4, 0.01), (6, 0.02)):
        means[row] = cube_b + offset
    table["means"].data.copy_(means)
    table["log_scales"].data.copy_(torch.log(torch.tensor([0.01, 0.004, 0.002])).expand(n, 3))
    opacity = torch.full((n,), 0.5)
    opacity[:3] = torch.tensor([0.2, 0.6, 0.4])
    table["opacity_logits"].data.copy_(torch.log(opacity / (1 - opacity)))
    for key in ("grad_sum", "flow_w", "resid_w", "help_dot", "help_norm"):
        state[key] = torch.zeros(n)
    state["steps_seen"] = torch.full((1,), 8.0)
    state["alive_count"] = state["vis_count"] = torch.full((n,), 8.0)
    state["front_count"] = torch.full((n,), 8.0)
    state["depth_total"] = torch.full((n,), 6.0)
    state["front_total"] = torch.full((n,), 3.0)
    state["front_total"][[0, 1, 2, 3, 4, 6]] = 0.0
    state["front_total"][5] = 1.0
    state["depth_total"][6] = 2.0
    monkeypatch.setattr(strategy, "_accumulate", lambda state, inputs: None)  # the sums above stand
    monkeypatch.setattr(strategy, "_accumulate_help", lambda model, state, inputs: None)
    before = {name: table[name].detach().clone() for name in ("means", "log_scales", "features")}
    iteration = 12  # > start_iter, (12 - 4) % 8 == 0, before densification stops
    assert strategy.active(iteration)
    report = strategy.step_post_backward(model, trainer.optimizer, state, density_step_inputs(iteration))
    return report, before, table, state


def test_unseen_surface_keeps_one_gaussian_per_cube(tiny_frames, monkeypatch):
    """Rows 0 and 2 go (row 1, the most opaque, covers cube A), one of rows 3-4 goes (a tie: the first
    stays); rows 5 (seen) and 6 (too young) stay, as every other row. A cover takes its cube's
    opacity-weighted mean centre and appearance, keeps its opacity, widens its two larger axes to
    0.6 x the cube (model.init_scale_factor) and keeps its thin one; the other rows are untouched."""
    report, before, table, state = _one_density_step(tiny_frames, monkeypatch, CELL)
    assert report["unseen_thinned"] == 3 and report["pruned"] == 0
    n = before["means"].shape[0]
    kept = [r for r in range(n) if r not in (0, 2, 4)]
    assert table.num == n - 3
    covers = [0, 1]  # rows 1 and 3 of the old table
    others = [i for i, r in enumerate(kept) if r not in (1, 3)]
    assert torch.equal(table["means"].detach()[others], before["means"][kept][others])
    # a cover's centre and appearance: the opacity-weighted means of its cube's unseen rows
    weights = {0: 0.2, 1: 0.6, 2: 0.4, 3: 0.5, 4: 0.5}
    for cover, cube in zip(covers, ((0, 1, 2), (3, 4)), strict=True):
        w = torch.tensor([weights[r] for r in cube])
        for name in ("means", "features"):
            expected = (before[name][list(cube)] * w[:, None]).sum(0) / w.sum()
            assert torch.allclose(table[name].detach()[cover], expected, atol=1e-6), name
    assert state["front_total"].shape[0] == n - 3  # the state follows the rows
    scales = table["log_scales"].detach().exp()
    side = 0.6 * CELL  # model.init_scale_factor x the cube, as the initial samples to their spacing
    for cover in covers:
        assert scales[cover].tolist() == pytest.approx([side, side, 0.002], rel=1e-5)
    assert table.opacities().detach()[covers].tolist() == pytest.approx([0.6, 0.5], rel=1e-5)  # their own
    assert torch.equal(table["log_scales"].detach()[others], before["log_scales"][kept][others])
    assert math.isclose(float(scales[2, 0]), 0.01, rel_tol=1e-5)  # row 5: seen, its size kept


def test_without_the_rule_unseen_surface_keeps_its_density(tiny_frames, monkeypatch):
    """unseen_cell_m = 0 (off; the behaviour before): the same table loses nothing."""
    report, before, table, _ = _one_density_step(tiny_frames, monkeypatch, 0.0)
    assert "unseen_thinned" not in report and report["pruned"] == 0
    assert torch.equal(table["means"].detach(), before["means"])
    assert torch.equal(table["log_scales"].detach(), before["log_scales"])


def test_the_rule_is_idempotent(tiny_frames, monkeypatch):
    """A second density step on the thinned table finds one unseen row per cube: nothing more goes."""
    from types import SimpleNamespace

    from stg_node.avatar.densify import DensifyStrategy

    _, _, table, state = _one_density_step(tiny_frames, monkeypatch, CELL)
    config = small_config(**{"densify.unseen_cell_m": CELL, "densify.unseen_after_views": AFTER})
    logs = table["log_scales"].detach().clone()
    model = SimpleNamespace(table=table, device=logs.device, config=config.model)  # what _thin_unseen reads
    drop = DensifyStrategy(config.densify, 100)._thin_unseen(model, state)
    assert not bool(drop.any())
    assert torch.equal(table["log_scales"].detach(), logs)


def test_a_negative_cube_is_refused():
    with pytest.raises(ValueError, match="unseen_cell_m"):
        small_config(**{"densify.unseen_cell_m": -0.1}).validate()


def test_training_steps_count_each_rows_sightings_with_the_rule_on(tiny_frames):
    """With the rule on, the steps themselves feed its counters (on a CPU the sightings kernel does
    not keep them, so the step takes the torch path): rows the camera sees as the surface count as
    seen, and every depth-tested step counts for all rows."""
    config = small_config(**{"densify.start_iter": 1, "densify.unseen_cell_m": CELL})
    trainer = Trainer(config, seed=0)
    trainer.add_frames(tiny_frames)
    for _ in range(4):
        trainer.step()
    state = trainer.densify_state
    assert float(state["depth_total"].max()) > 0
    assert 0 < int((state["front_total"] > 0).sum()) < trainer.model.table.num
