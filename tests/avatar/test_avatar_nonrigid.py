"""The non-rigid part earns its place: the decision (evidence, switch-off, forced choices), the held-out
frames of the trial, the rigid model a switch-off continues with, and the gain's arithmetic."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from avatar_helpers import density_step_inputs, small_config

from stg_node.avatar import nonrigid
from stg_node.avatar.trainer import Trainer


def _trial_config(**changes):
    """Shared bases, a trial of 12 steps on every 3rd frame held out, 20 steps in all."""
    base = {
        "model.motion_basis": 24,
        "iterations": 20,
        "nonrigid_decide_iter": 12,
        "nonrigid_holdout_every": 3,
        "densify.start_iter": 4,
        "densify.interval": 4,
    }
    return small_config(**(base | changes))


def _trainer(frames, config, steps):
    trainer = Trainer(config, seed=0)
    trainer.add_frames(frames)
    drawn = [trainer.step().frame for _ in range(steps)]
    return trainer, drawn


def test_validation_gain_pools_squared_errors_over_the_pixels_the_terms_change(monkeypatch):
    """Two 1x4 views; the renders differ on 3 pixels. Full-model errors there 0.1, 0.1 and 0 (the last
    view's), rigid-model errors 0.2, 0.2, 0.2: gain = 10 log10((3 x 0.04) / (2 x 0.01)) = 7.78 dB."""
    target = torch.zeros(1, 4, 3)
    renders = iter(
        [
            torch.tensor([[0.1, 0.1, 0.5, 0.0]]),  # view 1, full model
            torch.tensor([[0.2, 0.2, 0.5, 0.0]]),  # view 1, rigid part: differs on pixels 0, 1
            torch.tensor([[0.0, 0.3, 0.0, 0.0]]),  # view 2, full model
            torch.tensor([[0.2, 0.3, 0.0, 0.0]]),  # view 2, rigid part: differs on pixel 0
        ]
    )
    monkeypatch.setattr(nonrigid, "_render", lambda *a: next(renders)[..., None].expand(1, 4, 3))
    out = nonrigid.validation_gain(None, None, [(None, None, 0.0, target), (None, None, 0.1, target)])
    assert out["gain_db"] == pytest.approx(10 * math.log10(3 * 0.04 / (2 * 0.01)), rel=1e-5)
    assert out["changed_fraction"] == pytest.approx(3 / 8)
    whole_full = (0.01 * 2 + 0.25 + 0.09) / 8
    assert out["psnr_full"] == pytest.approx(-10 * math.log10(whole_full), rel=1e-5)


def test_a_trial_holds_frames_out_and_nothing_moving_switches_the_part_off(tiny_frames, tmp_path):
    """No Gaussian sees flow the rigid model misses: at the decision the trainer drops the motion
    columns, carries on as LBS only, says why, and a checkpoint keeps the choice; the held-out frames
    are never drawn during the trial and are drawn after it."""
    config = _trial_config()
    trainer, drawn = _trainer(tiny_frames, config, 12)
    held = {f.index for f in tiny_frames if nonrigid.held_out(f.index, 3)}
    assert held and not held & set(drawn)
    trainer.densify_state["resid_w"].fill_(0.01)  # seen, but everything explained
    before = trainer.model.table.num
    drawn = [trainer.step().frame for _ in range(8)]  # the decision, then 8 steps as LBS only
    assert trainer.decision.chose == "off" and trainer.decision.iteration == 12
    assert "rigid model explains the motion" in trainer.decision.why
    assert trainer.config.model.spacetime is False and trainer.config.densify.flow_guided is False
    assert not {"motion_coef", "motion_gate", "t_center"} & set(trainer.model.table.names())
    assert trainer.model.motion_bases is None and trainer.stats()["active_motion_fraction"] == 0.0
    assert trainer.model.table.num >= before - 50  # the same Gaussians (densification may prune a few)
    assert held & set(drawn) or len(held) * 8 < len(tiny_frames)  # held-out frames train again
    report = trainer.nonrigid_report()
    assert report["chose"] == "off" and report["evidence"]["moving_fraction"] == 0.0
    resumed = Trainer.load(trainer.save(tmp_path / "ck.stgsnap"))
    assert resumed.decision == trainer.decision and resumed.config.model.spacetime is False
    resumed.add_frames(tiny_frames)
    assert not resumed._deciding()


def test_a_switch_off_restarts_the_density_interval_and_the_rigid_model_densifies_on_its_own(tiny_frames):
    """The trial ends "off" at step 12, on a density step (start 4, interval 4). The interval's screen
    gradients were gathered by the model with motion terms, whose moving rows the switch-off snaps
    back: the statistics restart, step 12 clones nothing (one step of them is less than half an
    interval) and the interval runs on to step 16, which densifies on the rigid model's own four
    steps (and starts the next interval). Before the rule, step 12 cloned on the old statistics."""
    changes = {"iterations": 40, "densify.grad_threshold": 0.0, "densify.resample_fraction": 0.0}
    config = _trial_config(**changes)
    trainer, _ = _trainer(tiny_frames, config, 12)
    trainer.densify_state["resid_w"].fill_(0.01)  # nothing moves that the rigid model misses
    at_decision = trainer.step()
    assert trainer.decision.chose == "off" and trainer.decision.iteration == 12
    assert "cloned" not in at_decision.densify, at_decision.densify
    assert float(trainer.densify_state["steps_seen"]) == 1.0  # the interval restarted and runs on
    reports = [trainer.step().densify for _ in range(4)]  # steps 13-16
    assert [("cloned" in r) for r in reports] == [False, False, False, True], reports
    assert reports[-1]["cloned"] > 0 and float(trainer.densify_state["steps_seen"]) == 0.0


@pytest.mark.parametrize("gain, chose", [(1.0, "on"), (0.1, "off")])
def test_with_motion_the_held_out_gain_decides(tiny_frames, monkeypatch, gain, chose):
    config = _trial_config()
    trainer, _ = _trainer(tiny_frames, config, 12)
    trainer.densify_state["resid_w"].fill_(10.0)  # everything moves
    seen = []

    def fake_gain(model, rigid, views, backend):
        seen.extend(view[2] for view in views)
        assert "motion_coef" not in rigid.table.names() and "motion_coef" in model.table.names()
        return {"gain_db": gain, "changed_fraction": 0.2, "psnr_full": 30.0, "psnr_rigid": 29.0}

    monkeypatch.setattr(nonrigid, "validation_gain", fake_gain)
    trainer.step()
    held_times = {trainer.model.time_axis(f.time) for f in tiny_frames if nonrigid.held_out(f.index, 3)}
    assert set(seen) == held_times  # judged on the held-out frames, at their own times
    assert trainer.decision.chose == chose and f"{gain:+.2f} dB" in trainer.decision.why
    assert ("motion_coef" in trainer.model.table.names()) == (chose == "on")


def test_the_moving_share_counts_learned_motion_only_where_it_is_given():
    """Four Gaussians seen, one with missed flow above the threshold, two with their motion terms on
    (one of them the same): 1/4 on the flow alone, 2/4 with the motion terms; unseen rows never count."""
    resid = torch.tensor([2.0, 0.1, 0.1, 0.2, 5.0])
    seen = torch.tensor([True, True, True, True, False])
    terms = torch.tensor([True, True, False, False, True])
    assert nonrigid.moving_fraction(resid, seen, 1.5) == pytest.approx(1 / 4)
    assert nonrigid.moving_fraction(resid, seen, 1.5, terms) == pytest.approx(2 / 4)


@pytest.mark.parametrize("cameras, chose", [(1, "off"), (2, "on")])
def test_from_several_cameras_motion_the_terms_already_follow_counts_as_missed(
    tiny_frames, monkeypatch, cameras, chose
):
    """At the decision the flow is explained everywhere (the full model's motion follows it) and 30 %
    of the Gaussians move with their own terms. From one camera that is no evidence (off at the first
    test, as before); from two it is motion the rigid model misses, so the held-out gain decides."""
    import dataclasses

    from stg_node.avatar.frames import TrainFrame

    frames = list(tiny_frames)
    if cameras == 2:  # the same views again, as a second camera of the rig
        frames += [
            TrainFrame(f.index, f.time, f.image, f.mask, dataclasses.replace(f.camera, name="B"), f.smpl)
            for f in tiny_frames
        ]
    trainer, _ = _trainer(frames, _trial_config(), 12)
    assert len(trainer.camera_slots) == cameras
    trainer.densify_state["resid_w"].fill_(0.01)  # seen, every flow explained by the full model
    gate = trainer.model.table["motion_gate"]
    gate.data[:] = 0.0
    gate.data[: int(0.3 * gate.shape[0])] = 1.0
    gains = {"gain_db": 1.0, "changed_fraction": 0.2, "psnr_full": 30.0, "psnr_rigid": 29.0}
    monkeypatch.setattr(nonrigid, "validation_gain", lambda *a: gains)
    trainer.step()
    assert trainer.decision.chose == chose
    assert trainer.decision.evidence["moving_fraction"] == pytest.approx(
        0.0 if cameras == 1 else 0.3, abs=0.01
    )


def test_forced_on_never_decides_and_short_runs_keep_every_frame(tiny_frames):
    trainer, drawn = _trainer(tiny_frames, _trial_config(nonrigid="on"), 20)
    assert trainer.decision is None and trainer.nonrigid_report()["why"].startswith("nonrigid=on")
    assert "motion_coef" in trainer.model.table.names()
    short, _ = _trainer(tiny_frames, _trial_config(iterations=10), 10)
    assert not short._deciding() and len(short._training_frames()) == len(tiny_frames)
    assert short.nonrigid_report()["why"].startswith("no trial")
    off = Trainer(_trial_config(nonrigid="off"), seed=0)
    assert off.config.model.spacetime is False and off.config.densify.flow_guided is False
    assert off.nonrigid_report() == {"chose": "off", "why": "nonrigid=off: LBS only from the start"}
    with pytest.raises(ValueError, match="nonrigid must be one of"):
        _trial_config(nonrigid="maybe").validate()


def test_the_rigid_part_renders_like_the_model_with_its_terms_at_zero(tiny_frames):
    """With every motion term zero and no temporal copies, dropping the non-rigid part changes no pixel;
    Gaussians on a finite temporal window are dropped."""
    from stg_node.avatar.model import Camera3

    config = _trial_config(nonrigid="on")
    trainer, _ = _trainer(tiny_frames, config, 2)
    model = trainer.model
    rigid, keep = nonrigid.rigid_part(model)
    assert bool(keep.all()) and rigid.table.num == model.table.num
    frame = tiny_frames[3]
    camera = Camera3.from_camera(frame.camera)
    body = trainer.body_state(frame)
    u = model.time_axis(frame.time)
    a = nonrigid._render(model, camera, body, u, "auto")
    b = nonrigid._render(rigid, camera, body, u, "auto")
    assert torch.equal(a, b)
    with torch.no_grad():
        model.table["t_log_scale"][:5] = math.log(0.2)
    _, keep = nonrigid.rigid_part(model)
    assert keep.tolist()[:6] == [False] * 5 + [True] and int(keep.sum()) == model.table.num - 5


def test_the_rigid_part_keeps_each_moving_rows_mean_offset_over_the_knots(tiny_frames):
    """A moving row's offset averaged over the knot times (MotionBases.apply at each knot, the offset the
    model poses with) goes into its rigid centre; static rows keep theirs exactly."""
    from stg_node.avatar.motion_basis import MotionBases

    model = _moving(tiny_frames, rows=4, spread=0.01)
    table, bases = model.table, model.motion_bases
    means = table["means"].detach()
    knot_times = [int(k) * bases.knot_units for k in bases.knot_ids]
    offsets = [
        MotionBases.apply(bases.at(u).detach(), table["motion_coef"].detach()[:4], means[:4])
        for u in knot_times
    ]
    expected = means.clone()
    expected[:4] += torch.stack(offsets).mean(dim=0)
    rigid, keep = nonrigid.rigid_part(model)
    assert bool(keep.all())
    assert torch.allclose(rigid.table["means"], expected, atol=1e-6)
    assert torch.equal(rigid.table["means"][4:], means[4:])
    assert float((expected[:4] - means[:4]).norm(dim=1).min()) > 1e-4  # the fold moved every moving row


def test_runs_stored_before_the_trial_and_the_bases_resume_as_they_were():
    """A config or snapshot written before these settings existed keeps the polynomial motion, no
    trial, no settling and raw-flow seeds (what those runs did), not today's defaults."""
    from stg_node.avatar.config import ModelConfig, TrainConfig
    from stg_node.avatar.snapshot import model_config_from_meta, model_config_meta

    old = TrainConfig().to_dict()
    del old["nonrigid"], old["model"]["motion_basis"]
    del old["densify"]["motion_min_px"], old["densify"]["flow_seed_missed"]
    restored = TrainConfig.from_dict(old)
    assert restored.nonrigid == "on" and restored.model.motion_basis == 0
    # nor settling of small swings, and seeds on raw flow
    assert restored.densify.motion_min_px == 0.0 and not restored.densify.flow_seed_missed
    assert TrainConfig().densify.motion_min_px > 0 and TrainConfig().densify.flow_seed_missed
    assert TrainConfig.from_dict(TrainConfig().to_dict()) == TrainConfig()
    meta = model_config_meta(ModelConfig())
    assert model_config_from_meta(meta).motion_basis == ModelConfig().motion_basis == 24
    del meta["model.motion_basis"]
    assert model_config_from_meta(meta).motion_basis == 0


def test_a_gate_opens_on_flow_the_model_misses_or_where_moving_helps_not_on_motion_skinning_explains(
    tiny_frames,
):
    """Row 0: large flow the model's own motion explains (a turn): stays static. Row 1: flow it misses
    and the image pulls: opens. Row 2: no missed flow, but moving with its bones' shared motions
    would lower the loss (the normalised sum -<g, m> = 0.8): opens. Row 3: pulled, but moving would
    raise the loss: stays static. Each newly moving row starts with its skinning weights as
    coefficients. In the last round none opens."""
    from types import SimpleNamespace

    from stg_node.avatar.motion_basis import initial_coefficients

    trainer, _ = _trainer(tiny_frames, _trial_config(nonrigid="on"), 1)
    model, state, c = trainer.model, trainer.densify_state, trainer.config.densify
    n = model.table.num
    for key in ("flow_w", "resid_w", "help_dot", "help_norm"):
        state[key] = torch.zeros(n)
    state["flow_w"][0] = 50.0
    state["resid_w"][1] = 2 * c.residual_motion_px
    state["help_dot"][2], state["help_norm"][2] = -0.8, 1.0
    state["help_dot"][3], state["help_norm"][3] = 0.8, 1.0
    grads = torch.zeros(n)
    grads[:4] = c.grad_threshold  # the image pulls on all four
    inputs = SimpleNamespace(motion_threshold_px=1.0)
    report = trainer.densifier._gate_motion(model, trainer.optimizer, state, inputs, grads)
    gate = model.table.motion_gate()
    assert gate[:4].tolist() == [False, True, True, False] and report["motion_on"] == 2
    expected = initial_coefficients(model.skin_weights().detach()[1:3], model.motion_bases.count)
    assert torch.allclose(model.table["motion_coef"].detach()[1:3], expected)
    assert not bool(model.table["motion_coef"].detach()[[0, 3]].any())
    # The last round before densification stops opens nothing: no later round could settle it.
    model.table["motion_gate"].data.zero_()
    state["was_dynamic"].zero_()
    state["help_dot"][2], state["help_norm"][2] = -0.8, 1.0
    report = trainer.densifier._gate_motion(model, trainer.optimizer, state, inputs, grads, last_round=True)
    assert not bool(model.table.motion_gate().any()) and report["motion_on"] == 0


def test_motion_no_view_can_measure_settles_and_keeps_its_mean_offset(tiny_frames):
    """Two dynamic rows follow basis 0 alone: a constant 2 cm shift along x at every knot, plus at the
    last knot a stretch along y (dy = 0.01 y), so row 0 (canonical y = 0.1 m) swings 1 mm and row 1
    (y = 3 m) 3 cm. Each is seen where a pixel spans 1 cm; with motion_min_px = 1.5 (1.5 cm) row 0
    settles: its terms become exact zeros and its centre moves by its offset's mean over the knots
    (by hand: 2 cm along x, 1 mm / K along y); row 1 keeps moving, its centre unchanged."""
    from types import SimpleNamespace

    trainer, _ = _trainer(tiny_frames, _trial_config(nonrigid="on", **{"densify.motion_min_px": 1.5}), 1)
    model, state = trainer.model, trainer.densify_state
    table, bases = model.table, model.motion_bases
    n, knots = table.num, bases.knots
    table["motion_gate"].data.zero_()
    table["motion_gate"].data[:2] = 1.0
    state["was_dynamic"] = table["motion_gate"].detach().clone()
    state["m_per_px"] = torch.full((n,), 0.01)
    for key in ("resid_w", "flow_w", "help_dot", "help_norm"):
        state[key] = torch.zeros(n)
    if "rot_motion" in table:
        table["rot_motion"].data.zero_()
    table["motion_coef"].data.zero_()
    table["motion_coef"].data[:2, 0] = 1.0
    values = torch.zeros_like(bases.values)
    values[0, :, 0, 3] = 0.02
    values[0, -1, 1, 1] = 0.01
    bases.values.data.copy_(values)
    table["means"].data[:2, 1] = torch.tensor([0.1, 3.0])
    centres = table["means"].detach()[:2].clone()
    swing = torch.tensor([0.001, 0.03])
    assert float(swing[0] * (1 - 1 / knots)) < 0.015 < float(swing[1] * (1 - 1 / knots))
    report = trainer.densifier._gate_motion(
        model, trainer.optimizer, state, SimpleNamespace(motion_threshold_px=1.0), torch.zeros(n)
    )
    assert model.table.motion_gate()[:2].tolist() == [False, True] and report["motion_off"] == 1
    assert not bool(table["motion_coef"].detach()[0].any())
    expected = centres[0] + torch.tensor([0.02, 0.001 / knots, 0.0])
    assert torch.allclose(table["means"].detach()[0], expected, atol=1e-6)
    assert torch.equal(table["means"].detach()[1], centres[1])


def test_a_pixel_spans_depth_over_focal_at_each_gaussian_running_mean():
    """What one pixel spans at a Gaussian (metres), the scale motion_min_px is read in: depth / fx at
    its first sighting, then the running mean of later ones (the flow's decay, W_DECAY); rows not seen
    keep 0 (the absolute floor motion_min_m applies to them)."""
    from types import SimpleNamespace

    from stg_node.avatar.config import DensifyConfig
    from stg_node.avatar.densify import W_DECAY, DensifyStrategy

    n = 3
    state = {
        k: torch.zeros(n) for k in ("grad_sum", "vis_count", "front_count", "flow_w", "resid_w", "m_per_px")
    }
    state["steps_seen"] = torch.zeros(1)
    means2d = torch.zeros(n, 2, requires_grad=True)
    means2d.grad = torch.ones(n, 2)
    camera = SimpleNamespace(K=torch.tensor([[500.0, 0, 50], [0, 500.0, 50], [0, 0, 1]]))

    def step(depths, radii):
        info = {"radii": torch.tensor(radii), "means2d": means2d, "depths": torch.tensor(depths)}
        inputs = SimpleNamespace(
            info=info, index=None, crop=(0, 0, 100, 100), flow=None, camera=camera, rendered_depth=None
        )
        DensifyStrategy(DensifyConfig(clone_on_error=False), 100)._accumulate(state, inputs)

    step([2.0, 3.0, 4.0], [1, 1, 0])
    assert torch.allclose(state["m_per_px"], torch.tensor([2.0 / 500, 3.0 / 500, 0.0]))
    step([4.0, 3.0, 4.0], [1, 0, 0])
    expected0 = W_DECAY * 2.0 / 500 + (1 - W_DECAY) * 4.0 / 500
    assert torch.allclose(state["m_per_px"], torch.tensor([expected0, 3.0 / 500, 0.0]))


def test_flow_guided_seeds_sit_on_motion_the_model_misses_not_on_motion_it_follows():
    """Row 0: fast raw flow the model's motion follows (a turn); row 1: slow, but missed by 2 px;
    row 2: neither. Seeds need the missed flow (row 1); with flow_seed_missed off, or when the step
    did not render its motion, the raw flow above delta (row 0), as STG-Avatar's rule."""
    import dataclasses
    from types import SimpleNamespace

    from stg_node.avatar.config import DensifyConfig
    from stg_node.avatar.densify import DensifyStrategy

    state = {"flow_w": torch.tensor([6.0, 0.5, 0.2]), "resid_w": torch.tensor([0.3, 2.0, 0.1])}
    rows = torch.arange(3)
    rendered = SimpleNamespace(motion_threshold_px=1.0, rendered_flow=torch.zeros(1, 1, 2), camera_slot=0)
    unrendered = SimpleNamespace(motion_threshold_px=1.0, rendered_flow=None, camera_slot=0)
    config = DensifyConfig(residual_motion_px=1.5)
    assert DensifyStrategy(config, 100)._seed_motion(state, rows, rendered).tolist() == [False, True, False]
    assert DensifyStrategy(config, 100)._seed_motion(state, rows, unrendered).tolist() == [True, False, False]
    raw = DensifyStrategy(dataclasses.replace(config, flow_seed_missed=False), 100)
    assert raw._seed_motion(state, rows, rendered).tolist() == [True, False, False]


def _missed_flow_step(state, slot: int, missed_px: float, config=None) -> None:
    """One step's statistics for one Gaussian at pixel (2, 2) of an 8x8 crop, seen by training camera
    ``slot``, where the flow is ``missed_px`` along x and the model renders no motion."""
    from types import SimpleNamespace

    from stg_node.avatar.config import DensifyConfig
    from stg_node.avatar.densify import DensifyStrategy
    from stg_node.data.flow import FlowPair

    flow = np.zeros((8, 8, 2), np.float32)
    flow[..., 0] = missed_px
    valid = np.ones((8, 8), bool)
    means2d = torch.tensor([[2.0, 2.0]], requires_grad=True)
    means2d.grad = torch.zeros(1, 2)
    inputs = SimpleNamespace(
        info={"radii": torch.ones(1, dtype=torch.int32), "means2d": means2d},
        index=None,
        crop=(0, 0, 8, 8),
        flow=FlowPair(forward=flow, backward=-flow, valid_forward=valid, valid_backward=valid),
        camera=SimpleNamespace(K=torch.eye(3)),
        rendered_flow=torch.zeros(8, 8, 2),
        rendered_depth=None,
        camera_slot=slot,
        motion_threshold_px=1.0,
    )
    DensifyStrategy(config or DensifyConfig(clone_on_error=False), 100)._accumulate(state, inputs)


def _fresh_state(n: int = 1) -> dict:
    from stg_node.avatar.densify import ROW_STATE

    return {k: torch.zeros(n) for k in ROW_STATE} | {"steps_seen": torch.zeros(1)}


def test_missed_flow_is_the_most_any_training_camera_sees_not_the_mean_over_cameras():
    """A hem swinging toward camera A and across camera B's image: B sees 2.5 px a frame the model
    misses, A (looking along the swing) 0 px. Interleaved, a running mean over both cameras would
    stay near 1.3 px, under the 1.5 px threshold; per camera it is B's running mean, in closed form
    2.5 (1 - W^k) after B's k
    sightings, and A's column stays 0. The step's own camera decides a flow-guided seed (it moves
    along that camera's flow): a seed on B's steps, none on A's."""
    from types import SimpleNamespace

    from stg_node.avatar.config import DensifyConfig
    from stg_node.avatar.densify import W_DECAY, DensifyStrategy

    state = _fresh_state()
    for _ in range(20):
        _missed_flow_step(state, 0, 0.0)
        _missed_flow_step(state, 1, 2.5)
    expected = 2.5 * (1 - W_DECAY**20)
    assert state["resid_cam"].shape == (1, 2)
    assert float(state["resid_cam"][0, 0]) == 0.0
    assert abs(float(state["resid_cam"][0, 1]) - expected) < 1e-5
    assert abs(float(state["resid_w"][0]) - expected) < 1e-5
    mixed = 0.0  # what one running mean over the interleaved readings gives: well under the threshold
    for _ in range(20):
        mixed = W_DECAY * (W_DECAY * mixed) + (1 - W_DECAY) * 2.5
    assert mixed < DensifyConfig().residual_motion_px < float(state["resid_w"][0])
    strategy = DensifyStrategy(DensifyConfig(residual_motion_px=1.5), 100)
    rows = torch.arange(1)
    on = [
        strategy._seed_motion(state, rows, SimpleNamespace(rendered_flow=torch.zeros(1, 1, 2), camera_slot=s))
        for s in (0, 1)
    ]
    assert [bool(x) for x in on] == [False, True]


def test_with_one_camera_the_missed_flow_is_its_running_mean_as_before():
    """One training camera: the statistic is the plain running mean of the readings (closed form), so
    single-camera training reads the same numbers it did before cameras were told apart."""
    from stg_node.avatar.densify import W_DECAY

    state = _fresh_state()
    readings = [2.0, 0.5, 4.0, 1.0]
    expected = 0.0
    for r in readings:
        _missed_flow_step(state, 0, r)
        expected = W_DECAY * expected + (1 - W_DECAY) * r
    assert state["resid_cam"].shape == (1, 1)
    assert abs(float(state["resid_w"][0]) - expected) < 1e-6


def test_per_camera_statistics_follow_the_rows_when_gaussians_are_added_and_pruned():
    """Growing and pruning the table resizes the (n, cameras) statistic with the per-row ones."""
    from stg_node.avatar.densify import DensifyStrategy

    state = _fresh_state(3)
    state["resid_cam"] = torch.tensor([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]])
    DensifyStrategy._resize(state, keep=torch.tensor([True, False, True]), added=2)
    assert state["resid_cam"].tolist() == [[1.0, 2.0], [5.0, 6.0], [0.0, 0.0], [0.0, 0.0]]
    assert state["resid_w"].shape == (4,)


@pytest.mark.parametrize("on_error", [True, False])
def test_the_clone_signal_counts_each_step_in_proportion_to_its_regions_error(on_error):
    """Three Gaussians seen in three 8 px tiles of a 16x16 crop whose mean |render - gt| is half of tau,
    twice tau and zero: their screen gradients (|g| x crop pixels, AbsGS) count x0.5, x1 (capped) and
    x0 into the clone statistic; with clone_on_error off every one counts in full (3DGS / AbsGS)."""
    from types import SimpleNamespace

    from stg_node.avatar.config import DensifyConfig
    from stg_node.avatar.densify import DensifyStrategy

    tau = 0.08
    target = torch.zeros(16, 16, 3)
    render = torch.zeros(16, 16, 3)
    render[:8, :8] = 0.5 * tau  # tile (0, 0): every pixel off by tau / 2 in every channel
    render[:8, 8:, 0] = 6 * tau  # tile (0, 1): one channel off by 6 tau, so the mean over RGB is 2 tau
    n = 3
    names = ("grad_sum", "vis_count", "front_count", "flow_w", "resid_w", "m_per_px")
    state = {k: torch.zeros(n) for k in names}
    state["steps_seen"] = torch.zeros(1)
    means2d = torch.tensor([[3.0, 4.0], [12.0, 2.0], [5.0, 13.0]], requires_grad=True)  # (x, y)
    means2d.absgrad = torch.tensor([[3.0, 4.0], [0.6, 0.8], [1.0, 0.0]])  # |g| = 5, 1, 1
    info = {"radii": torch.ones(n, dtype=torch.int32), "means2d": means2d}
    inputs = SimpleNamespace(
        info=info,
        index=None,
        crop=(0, 0, 16, 16),
        flow=None,
        render=render,
        target=target,
        rendered_depth=None,
    )
    config = DensifyConfig(region_px=8, error_threshold=tau, clone_on_error=on_error)
    DensifyStrategy(config, 100)._accumulate(state, inputs)
    weights = torch.tensor([0.5, 1.0, 0.0]) if on_error else torch.ones(3)
    assert torch.allclose(state["grad_sum"], torch.tensor([5.0, 1.0, 1.0]) * 256 * weights)
    assert state["vis_count"].tolist() == [1.0, 1.0, 1.0]


@pytest.mark.parametrize("occlusion_m, back_reads_flow", [(0.04, False), (0.0, True)])
def test_a_gaussian_hidden_behind_the_surface_does_not_read_its_occluders_flow(occlusion_m, back_reads_flow):
    """Two opaque Gaussians on one line of sight, 2.0 m and 2.6 m from the camera (rendered by the real
    rasterizer, with its depth): the flow under both centres is the front one's (3 px). Only the front
    one accumulates it; the hidden one keeps zero, unless the occlusion test is off (occlusion_m=0, the
    behaviour before: every Gaussian under the pixel reads it). The surface depth is the front one's."""
    from types import SimpleNamespace

    from stg_node.avatar.config import DensifyConfig
    from stg_node.avatar.densify import DensifyStrategy, surface_depth
    from stg_node.data.flow import FlowPair
    from stg_node.splat.api import rasterize

    size = 64
    means = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 2.6]], requires_grad=True)
    K = torch.tensor([[100.0, 0, size / 2], [0, 100.0, size / 2], [0, 0, 1]])
    image, alpha, info = rasterize(
        means,
        torch.tensor([[1.0, 0, 0, 0]] * 2),
        torch.full((2, 3), 0.1),
        torch.tensor([0.99, 0.99]),
        torch.rand(2, 3),
        torch.eye(4),
        K,
        size,
        size,
        render_depth=True,
    )
    info["means2d"].retain_grad()
    image.sum().backward()
    depth = surface_depth(info["depth"], alpha)
    assert abs(float(depth[size // 2, size // 2]) - 2.0) < 0.05
    assert torch.isinf(depth[0, 0])  # nothing there

    flow = np.zeros((size, size, 2), np.float32)
    flow[..., 0] = 3.0
    valid = np.ones((size, size), bool)
    pair = FlowPair(forward=flow, backward=-flow, valid_forward=valid, valid_backward=valid)
    state = {
        k: torch.zeros(2) for k in ("grad_sum", "vis_count", "front_count", "flow_w", "resid_w", "m_per_px")
    }
    state["steps_seen"] = torch.zeros(1)
    inputs = SimpleNamespace(
        info=info,
        index=None,
        crop=(0, 0, size, size),
        flow=pair,
        camera=SimpleNamespace(K=K),
        rendered_flow=torch.zeros(size, size, 2),
        rendered_depth=depth,
        camera_slot=0,
    )
    DensifyStrategy(DensifyConfig(occlusion_m=occlusion_m), 100)._accumulate(state, inputs)
    assert float(state["resid_w"][0]) > 0 and float(state["flow_w"][0]) > 0
    assert (float(state["resid_w"][1]) > 0) == back_reads_flow
    assert (float(state["flow_w"][1]) > 0) == back_reads_flow
    # Both were rasterized; only the front one counts as seen (the motion gate's mean pull).
    assert state["vis_count"].tolist() == [1.0, 1.0]
    assert state["front_count"].tolist() == ([1.0, 1.0] if back_reads_flow else [1.0, 0.0])


def test_a_gate_round_on_a_density_step_reads_the_interval_that_ends_there(tiny_frames, monkeypatch):
    """A density step and a gate round on one step (the fast preset's schedule: every density step):
    the gate round must see the ending interval's mean pull (grad_sum / front_count), not the zeros of
    the next one. Row 0 sits on flow its motion misses and the image pulls on it at 0.75 x the clone
    threshold (above the gate's half, below cloning), so its gate opens; row 1, as pulled but on
    motion skinning explains, stays static. Then the next interval starts from zero."""

    changes = {
        "nonrigid": "on",
        "densify.start_iter": 4,
        "densify.gate_start_iter": 4,
        "densify.interval": 4,
        "densify.prune_opacity": 0.0,
        "densify.prune_score": 0.0,
        "densify.prune_scale_m": 1e9,
        "densify.resample_fraction": 0.0,
    }
    trainer, _ = _trainer(tiny_frames, _trial_config(**changes), 1)
    model, state, strategy = trainer.model, trainer.densify_state, trainer.densifier
    c = trainer.config.densify
    n = model.table.num
    model.table["motion_gate"].data.zero_()
    for key in ("flow_w", "resid_w", "help_dot", "help_norm", "was_dynamic", "grad_sum", "vis_count"):
        state[key] = torch.zeros(n)
    state["front_count"] = torch.zeros(n)
    state["resid_w"][0] = 2 * c.residual_motion_px
    state["grad_sum"][:2] = 3 * 0.75 * c.grad_threshold  # summed over three sightings: mean 0.75 x
    state["vis_count"][:2] = state["front_count"][:2] = 3.0
    state["steps_seen"] = torch.full((1,), 3.0)
    monkeypatch.setattr(strategy, "_accumulate", lambda state, inputs: None)  # the sums above stand
    monkeypatch.setattr(strategy, "_accumulate_help", lambda model, state, inputs: None)
    iteration = 8  # > start_iter, (8 - 4) % 4 == 0 for both schedules
    assert strategy.active(iteration)
    inputs = density_step_inputs(iteration)
    report = strategy.step_post_backward(model, trainer.optimizer, state, inputs)
    assert report["cloned"] == 0 and report["split"] == 0 and report["pruned"] == 0
    assert model.table.motion_gate()[:2].tolist() == [True, False] and report["motion_on"] == 1
    for key in ("grad_sum", "vis_count", "front_count", "steps_seen"):
        assert not bool(state[key].any()), key


def test_a_row_is_judged_on_the_steps_it_existed_in(tiny_frames, monkeypatch):
    """The contribution prune (opacity x fraction of steps seen < prune_score) on a density step that
    ends an 8-step interval. Row 0 was there all interval and never seen: pruned. Row 1 was added
    (along the flow) 2 steps before and seen in both: its fraction is 2/2, not 2/8, so it stays,
    though opacity x 2/8 is under the threshold. Row 2 was added this very step (a flow round on a
    density step): no statistics yet, it stays. Row 3, there all interval and seen every step: stays.
    Judged over the interval's 8 steps (the rule before), rows 1 and 2 would go."""

    changes = {
        "nonrigid": "on",
        "densify.start_iter": 4,
        "densify.gate_start_iter": 100,
        "densify.interval": 8,
        "densify.prune_opacity": 0.0,
        "densify.prune_score": 0.2,
        "densify.prune_scale_m": 1e9,
        "densify.resample_fraction": 0.0,
        "densify.grad_threshold": 1e9,
    }
    trainer, _ = _trainer(tiny_frames, _trial_config(**changes), 1)
    model, state, strategy = trainer.model, trainer.densify_state, trainer.densifier
    n = model.table.num
    model.table["opacity_logits"].data.fill_(0.0)  # opacity 0.5: 0.5 x 2/8 = 0.125 < 0.2 <= 0.5
    for key in ("grad_sum", "flow_w", "resid_w", "help_dot", "help_norm"):
        state[key] = torch.zeros(n)
    state["steps_seen"] = torch.full((1,), 8.0)
    state["alive_count"] = torch.full((n,), 8.0)
    state["vis_count"] = torch.full((n,), 8.0)
    state["front_count"] = state["vis_count"].clone()
    state["vis_count"][0] = 0.0
    state["alive_count"][1], state["vis_count"][1] = 2.0, 2.0
    state["alive_count"][2], state["vis_count"][2] = 0.0, 0.0
    monkeypatch.setattr(strategy, "_accumulate", lambda state, inputs: None)  # the sums above stand
    monkeypatch.setattr(strategy, "_accumulate_help", lambda model, state, inputs: None)
    means = model.table["means"].detach().clone()
    iteration = 12  # > start_iter, (12 - 4) % 8 == 0, before densification stops (15)
    assert strategy.active(iteration)
    inputs = density_step_inputs(iteration)
    report = strategy.step_post_backward(model, trainer.optimizer, state, inputs)
    assert report["pruned"] == 1 and report["cloned"] == 0
    assert torch.equal(model.table["means"].detach(), means[1:])  # row 0 went, the others stayed
    assert not bool(state["alive_count"].any())  # the next interval counts from zero


def test_a_checkpoint_without_per_row_step_counts_resumes_with_every_row_there_all_interval(
    tiny_frames, tmp_path, monkeypatch
):
    """A checkpoint written before ``alive_count`` was kept loads with it equal to the interval's
    step count for every row (the old rule: each row judged over the whole interval), not zeros,
    which would spare every row from the next prune."""
    from stg_node.avatar import checkpoint

    trainer, _ = _trainer(tiny_frames, _trial_config(**{"densify.interval": 8}), 6)
    steps = float(trainer.densify_state["steps_seen"])
    assert steps > 0
    path = trainer.save(tmp_path / "ck.stgsnap")
    read = checkpoint.read_snapshot_file

    def without_alive(p):
        msg = read(p)
        del msg.arrays["train.densify.alive_count"]
        return msg

    monkeypatch.setattr(checkpoint, "read_snapshot_file", without_alive)
    alive = checkpoint.load(path).densify["alive_count"]
    assert alive.shape == trainer.densify_state["vis_count"].shape
    assert bool((alive == steps).all())


def _moving(frames, rows: int | None = None, spread: float = 0.02):
    """A model whose first ``rows`` rows (all: None) move, differently at every knot (random bases of
    ``spread`` metres, random coefficients); the other rows are static (gate and coefficients 0)."""
    trainer, _ = _trainer(frames, _trial_config(nonrigid="on"), 2)
    model = trainer.model
    table, bases = model.table, model.motion_bases
    n = table.num if rows is None else rows
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        bases.values.copy_(spread * torch.randn(bases.values.shape, generator=g))
        table["motion_gate"].zero_()
        table["motion_gate"][:n] = 1.0
        table["motion_coef"][:n] = torch.rand(n, bases.count, generator=g)
        table["motion_coef"][n:] = 0.0
    return model


def test_a_pose_beyond_the_index_reach_renders_the_mean_placement_one_within_it_its_instant(tiny_frames):
    """Without a time, a pose as near a training pose as consecutive training poses are renders that
    instant's non-rigid state; one farther than twice that renders the rigid part (timecode.py: no
    instant stands for it)."""
    from stg_node.avatar.renderer import AvatarRenderer

    model = _moving(tiny_frames)
    renderer = AvatarRenderer(model)
    mean = AvatarRenderer(nonrigid.rigid_part(model)[0])
    frame = tiny_frames[3]
    camera = frame.camera
    index = model.pose_index
    near = frame.smpl
    u, _ = index.time_for(np.asarray(near.poses))
    at_instant = renderer.render(camera, near, model.time_axis.origin_s + u * model.time_axis.unit_s).image
    assert index.within_reach(np.asarray(near.poses))
    assert np.array_equal(renderer.render(camera, near).image, at_instant)
    far_poses = np.array(near.poses, np.float32).reshape(24, 3)
    far_poses[16] += [0.0, 0.0, 1.2]  # the left shoulder far beyond any training pose
    far = dataclasses.replace(near, poses=far_poses)
    assert index.trust(far_poses) == 0.0
    beyond = renderer.render(camera, far).image
    assert np.array_equal(beyond, mean.render(camera, far).image)
    assert np.array_equal(renderer.points(far).positions, mean.points(far).positions)  # as render poses it
    instant = renderer.render(camera, far, model.time_axis.origin_s + u * model.time_axis.unit_s).image
    assert not np.array_equal(beyond, instant)  # the motion terms do change this view


def test_an_animation_crossing_the_index_reach_changes_continuously_where_a_hard_switch_pops(tiny_frames):
    """A shoulder swung out of the training poses in 49 even steps, rendered without a time: from the
    reach to twice it the instant's motion terms fade out (timecode.PoseTimeIndex.trust), so no
    frame-to-frame change (mean absolute grey levels) exceeds 3x the largest the instant rule itself
    shows between the same neighbouring poses (rendered at the nearest instant throughout; the fade
    spreads the instant-to-mean change over one reach of pose, about 11 of these steps). Switching hard
    (round 10b's rule) changes the image at once by the instant-to-mean difference: 20x that step."""
    from stg_node.avatar.renderer import AvatarRenderer

    model = _moving(tiny_frames)
    renderer = AvatarRenderer(model)
    mean = AvatarRenderer(nonrigid.rigid_part(model)[0])
    frame = tiny_frames[3]
    index, axis = model.pose_index, model.time_axis
    faded, instant, weights, jumps = [], [], [], []
    for angle in np.linspace(0.0, 1.2, 49):
        poses = np.array(frame.smpl.poses, np.float32).reshape(24, 3)
        poses[16] += [0.0, 0.0, angle]  # the left shoulder, out of every training pose
        smpl = dataclasses.replace(frame.smpl, poses=poses)
        u, _ = index.time_for(poses)
        weight = index.trust(poses)
        image = renderer.render(frame.camera, smpl).image.astype(np.float64)
        at_instant = renderer.render(frame.camera, smpl, axis.origin_s + u * axis.unit_s).image
        at_instant = at_instant.astype(np.float64)
        at_mean = mean.render(frame.camera, smpl).image.astype(np.float64)
        if weight == 1.0:
            assert np.array_equal(image, at_instant)  # within the reach: the instant, bit for bit
        if weight == 0.0:
            assert np.array_equal(image, at_mean)  # from twice it on: the mean placement, bit for bit
        faded.append(image)
        instant.append(at_instant)
        weights.append(weight)
        jumps.append(float(np.abs(at_instant - at_mean).mean()))
    assert weights[0] == 1.0 and weights[-1] == 0.0

    def steps(images):
        return [float(np.abs(b - a).mean()) for a, b in zip(images[:-1], images[1:], strict=True)]

    bound = 3.0 * max(steps(instant))
    assert max(steps(faded)) <= bound
    assert sum(0.0 < w < 1.0 for w in weights) >= 8  # the fade spans many steps
    first_beyond = next(i for i, w in enumerate(weights) if w < 1.0)
    assert jumps[first_beyond] > 5.0 * bound  # what a hard switch there would change at once
