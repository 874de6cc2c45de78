"""A training step's per-step bookkeeping on the pose side, against plain per-row truth: the motion-help
sums of densification (densify._accumulate_help, dense and row-gathered paths) and the basis
coefficients a Gaussian starts to move with (motion_basis.initial_coefficients)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch
from avatar_helpers import small_config

from stg_node.avatar.motion_basis import NUM_BONES, initial_coefficients
from stg_node.avatar.rigid import SKIN_WEIGHT_EPS
from stg_node.avatar.trainer import Trainer


def test_initial_coefficients_sum_each_bases_bones():
    """Basis b of B takes the bones j with j * B // 24 == b; one bone per basis is the weights."""
    gen = torch.Generator().manual_seed(0)
    weights = torch.rand(7, NUM_BONES, generator=gen)
    for count in (1, 5, 8, 24):
        expected = torch.zeros(7, count, dtype=torch.float64)
        for j in range(NUM_BONES):
            expected[:, j * count // NUM_BONES] += weights[:, j].double()
        got = initial_coefficients(weights, count)
        assert got.shape == (7, count)
        torch.testing.assert_close(got.double(), expected, rtol=1e-6, atol=1e-7)
    assert initial_coefficients(weights, NUM_BONES).data_ptr() != weights.data_ptr()  # a copy


def _help_truth(model, grad, static, u):
    """help_dot, help_norm of one step, row by row in float64 from the definitions."""
    table = model.table
    delta = table["skin_delta"].detach().double()
    w = (table["skin_weights"].detach().double() + SKIN_WEIGHT_EPS) * delta.exp()
    w = w / w.sum(1, keepdim=True)
    count = model.motion_bases.count
    motions = model.motion_bases.at(u).detach().double()  # (B, 3, 4)
    x = table["means"].detach().double()
    dot = torch.zeros(table.num, dtype=torch.float64)
    norm = torch.zeros(table.num, dtype=torch.float64)
    for i in range(table.num):
        g = grad[i].double()
        if not bool(static[i]) or not bool((g != 0).any()):
            continue
        would = torch.zeros(3, dtype=torch.float64)
        for j in range(NUM_BONES):
            b = j * count // NUM_BONES
            would += w[i, j] * (motions[b, :, :3] @ x[i] + motions[b, :, 3])
        dot[i] = g @ would
        norm[i] = g.norm() * would.norm()
    return dot, norm


@pytest.mark.parametrize("count", [24, 8])
@pytest.mark.parametrize("moving_fraction", [0.1, 0.9])  # the dense path, the row-gathered path
def test_motion_help_sums_match_the_per_row_definition(tiny_frames, count, moving_fraction):
    config = small_config(**{"model.motion_basis": count, "nonrigid": "on", "iterations": 20})
    trainer = Trainer(config, seed=0)
    trainer.add_frames(tiny_frames)
    trainer.step()
    model, state = trainer.model, trainer.densify_state
    table = model.table
    n = table.num
    gen = torch.Generator().manual_seed(1)
    with torch.no_grad():
        table["skin_delta"].copy_(0.3 * torch.randn(table["skin_delta"].shape, generator=gen))
        model.motion_bases.values.copy_(0.05 * torch.randn(model.motion_bases.values.shape, generator=gen))
        table["motion_gate"].copy_((torch.rand(n, generator=gen) < moving_fraction).float())
    grad = torch.randn(n, 3, generator=gen)
    grad[torch.rand(n, generator=gen) < 0.3] = 0.0  # rows the step did not reach
    table["means"].grad = grad
    start_dot = torch.rand(n, generator=gen)
    start_norm = torch.rand(n, generator=gen)
    state["help_dot"], state["help_norm"] = start_dot.clone(), start_norm.clone()
    u = 0.37
    trainer.densifier._accumulate_help(model, state, SimpleNamespace(u=u))
    dot, norm = _help_truth(model, grad, ~table.motion_gate(), u)
    torch.testing.assert_close(state["help_dot"].double(), start_dot.double() + dot, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(state["help_norm"].double(), start_norm.double() + norm, rtol=1e-5, atol=1e-6)
    untouched = table.motion_gate() | (grad == 0).all(1)
    assert torch.equal(state["help_dot"][untouched], start_dot[untouched])  # exactly, not merely close
    assert torch.equal(state["help_norm"][untouched], start_norm[untouched])


def test_statistics_stop_with_the_schedule_and_training_is_unchanged(tiny_frames, monkeypatch):
    """Past the densification schedule (and with no non-rigid trial deciding) nothing reads the
    per-step statistics: the trainer stops gathering them, and the model it trains equals, bit for
    bit, one trained by the step before the change (statistics gathered on every step)."""
    from stg_node.avatar.densify import DensifyStrategy

    config = small_config(
        iterations=40, nonrigid="on", **{"densify.stop_fraction": 0.5, "model.motion_basis": 4}
    )
    gathered = []
    original = DensifyStrategy.step_post_backward

    def every_step(self, model, optimizer, state, inputs):  # the step before the change
        out = original(self, model, optimizer, state, inputs)
        if inputs.iteration >= int(self.config.stop_fraction * self.total):
            self._accumulate(state, inputs)
            self._accumulate_help(model, state, inputs)
        return out

    def counted(self, state, inputs):
        gathered.append(inputs.iteration)
        return accumulate(self, state, inputs)

    accumulate = DensifyStrategy._accumulate
    trained = {}
    for name in ("now", "before"):
        gathered.clear()
        with monkeypatch.context() as patch:
            patch.setattr(DensifyStrategy, "_accumulate", counted)
            if name == "before":
                patch.setattr(DensifyStrategy, "step_post_backward", every_step)
            trainer = Trainer(config, seed=0)
            trainer.add_frames(tiny_frames)
            for _ in range(config.iterations):
                trainer.step()
        trained[name] = {k: v.detach().clone() for k, v in trainer.model.state_dict().items()}
        if name == "now":
            assert gathered == list(range(20)), gathered
            assert trainer.model.motion_bases is not None
        else:
            assert gathered == list(range(40))
    assert trained["now"].keys() == trained["before"].keys()
    for key, value in trained["now"].items():
        assert torch.equal(value, trained["before"][key]), key
