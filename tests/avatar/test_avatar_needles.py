"""Streaks under extrapolated poses: the spill metric, the shape statistics, and the joint shrink."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from stg_node.data.metrics.spill import SpillScores


def _disc(shape, centre, radius):
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    return (yy - centre[0]) ** 2 + (xx - centre[1]) ** 2 <= radius**2


def test_spill_counts_alpha_beyond_the_margin_and_charges_the_nearest_part():
    """A square body of two parts (left half 'arms', right half 'torso'); the render covers it
    exactly, plus its antialiased rim (within the margin: not spill) and a streak 10 px long off the
    left side at alpha 0.8: 8 of those px lie beyond the 2 px margin, all charged to the arms."""
    truth = np.zeros((40, 40), bool)
    truth[10:30, 10:30] = True
    arms = truth.copy()
    arms[:, 20:] = False
    torso = truth & ~arms
    alpha = truth.astype(np.float64)
    alpha[9, 10:30] = 0.5  # the rim: one pixel above the top edge
    alpha[20, 0:10] = 0.8  # the streak, off the left (arms) side: distances 1..10 px
    scores = SpillScores(margin_px=2.0)
    scores.add(alpha, truth, {"arms": arms, "torso": torso})
    report = scores.report()
    beyond = 0.8 * 8  # distances 3..10
    assert report["spill_pct"] == pytest.approx(100 * beyond / truth.sum())
    assert report["regions"]["arms"]["spill_pct"] == pytest.approx(100 * beyond / arms.sum())
    assert report["regions"]["torso"]["spill_pct"] == 0.0
    assert report["covered_px"] == 8 and report["regions"]["arms"]["covered_px"] == 8


def test_spill_of_a_perfect_render_is_zero_and_uint8_inputs_scale():
    truth = _disc((64, 64), (32, 32), 15)
    scores = SpillScores()
    scores.add((truth * 255).astype(np.uint8), (truth * 255).astype(np.uint8))
    assert scores.report()["spill_pct"] == 0.0
    halo = _disc((64, 64), (32, 32), 25)  # a disc 10 px wider all round, alpha 1 in uint8
    scores = SpillScores(margin_px=0.0)
    scores.add((halo * 255).astype(np.uint8), truth)
    assert scores.report()["spill_pct"] == pytest.approx(100 * (halo & ~truth).sum() / truth.sum())
    with pytest.raises(ValueError, match="same"):
        scores.add(np.zeros((8, 8)), np.zeros((9, 9), bool))


def test_axis_ratios_and_neighbour_disagreement_against_hand_computed_values():
    from stg_node.avatar.shape_stats import axis_ratios, neighbour_disagreement

    scales = torch.tensor([[1.0, 1.0, 1.0], [0.1, 1.0, 1.0], [4.0, 1.0, 0.5]])
    scale_ratio, needle = axis_ratios(scales)
    np.testing.assert_allclose(scale_ratio.numpy(), [1.0, 10.0, 8.0])
    np.testing.assert_allclose(needle.numpy(), [1.0, 1.0, 4.0])  # the disc is no needle
    weights = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.5, 0.5, 0.0]])
    neighbours = torch.tensor([[1, 2], [0, 2], [0, 1]])
    np.testing.assert_allclose(neighbour_disagreement(weights, neighbours).numpy(), [0.75, 0.75, 0.5])


def _bent_elbow_pose(degrees: float) -> np.ndarray:
    from stg_node.body import SMPL_JOINT_NAMES

    poses = np.zeros((24, 3), np.float32)
    poses[SMPL_JOINT_NAMES.index("left_elbow"), 1] = -np.radians(degrees)
    return poses


def _bent_elbow_trainer(tiny_frames):
    """A 2-step trainer's model with the left elbow folded 150 degrees: (trainer, body, camera centre)."""
    from avatar_helpers import small_config

    from stg_node.avatar.model import BodyState
    from stg_node.avatar.trainer import Trainer
    from stg_node.body.params import SmplParams

    trainer = Trainer(small_config(iterations=2), seed=0)
    trainer.add_frames(tiny_frames[:2])
    smpl = tiny_frames[0].smpl
    bent = SmplParams(poses=_bent_elbow_pose(150.0), Rh=smpl.Rh, Th=smpl.Th, betas=smpl.betas)
    return trainer, BodyState.from_smpl(bent), torch.tensor([0.0, -3.0, 1.0])


def test_posing_shrinks_gaussians_between_bent_bones_only(tiny_frames):
    """A trained model posed with an elbow folded 150 degrees: with the joint shrink on, each
    Gaussian is rendered at its size times the squeeze of its bones' blend; one on a single bone is
    rendered at its size where its bones all turn alike; off, every Gaussian keeps its size."""
    import dataclasses

    from stg_node.avatar.rigid import joint_shrink

    trainer, body, centre = _bent_elbow_trainer(tiny_frames)
    model = trainer.model
    with torch.no_grad():
        on = model.pose(body, 0.0, centre, cull_transparent=False)
        factor = joint_shrink(model.skin_weights(), model.bones(body))
        model.config = dataclasses.replace(model.config, joint_shrink=False)
        off = model.pose(body, 0.0, centre, cull_transparent=False)
    assert model.config.joint_shrink is False and trainer.config.model.joint_shrink is True
    torch.testing.assert_close(off.scales, model.scales())
    torch.testing.assert_close(on.scales, off.scales * factor[:, None])
    from stg_node.body import SMPL_JOINT_NAMES

    forearm = [SMPL_JOINT_NAMES.index(n) for n in ("left_elbow", "left_wrist", "left_hand")]
    moved = model.skin_weights()[:, forearm].sum(dim=1)  # the bones the fold turns
    on_forearm, at_elbow = moved > 0.99, (moved > 0.3) & (moved < 0.7)
    assert bool(on_forearm.any()) and bool(at_elbow.any())
    assert bool((factor[on_forearm] > 0.95).all())  # bones that all turn alike: hardly squeezed
    # two bones 150 deg apart weighted 0.3 / 0.7 squeeze to 0.38, half and half to cos(75 deg) = 0.26
    assert bool((factor[at_elbow] < 0.4).all())


def test_a_model_from_before_the_joint_shrink_loads_without_it(tiny_frames):
    import dataclasses

    from avatar_helpers import small_config

    from stg_node.avatar.config import TrainConfig
    from stg_node.avatar.snapshot import model_from_snapshot
    from stg_node.avatar.trainer import Trainer

    trainer = Trainer(small_config(iterations=2), seed=0)
    trainer.add_frames(tiny_frames[:2])
    msg = trainer.snapshot()
    old = dataclasses.replace(msg, meta={k: v for k, v in msg.meta.items() if k != "model.joint_shrink"})
    assert model_from_snapshot(msg).config.joint_shrink is True
    assert model_from_snapshot(old).config.joint_shrink is False
    data = trainer.config.to_dict()
    del data["model"]["joint_shrink"]
    assert TrainConfig.from_dict(data).model.joint_shrink is False


def test_a_training_pose_takes_the_same_squeeze_and_differentiates_the_scales_through_it(tiny_frames):
    """With gradients on (a training step) the squeeze comes from the skinning kernel's blend, as a
    renderer's: the posed scales equal the table's times the torch factor (rigid.joint_shrink) to
    float rounding, and the scales' gradient is the factor's (the squeeze takes none itself)."""

    from stg_node.avatar.rigid import joint_shrink

    trainer, body, centre = _bent_elbow_trainer(tiny_frames)
    model = trainer.model
    posed = model.pose(body, 0.0, centre, cull_transparent=False)
    with torch.no_grad():
        factor = joint_shrink(model.skin_weights(), model.bones(body))
    assert bool((factor < 0.5).any())  # the fold squeezes some
    torch.testing.assert_close(
        posed.scales.detach(), model.scales().detach() * factor[:, None], atol=1e-6, rtol=1e-5
    )
    log_scales = model.table["log_scales"]
    (got,) = torch.autograd.grad(posed.scales.sum(), log_scales)
    (want,) = torch.autograd.grad((model.scales() * factor[:, None]).sum(), log_scales)
    torch.testing.assert_close(got, want, atol=1e-6, rtol=1e-5)
