"""Numerical stability of training and rendering at the extremes (docs/STABILITY.md): a sequence spanning
10,000 frames, very fast motion, poses at and beyond the joint limits, tiny and large images, scales
from 1e-6 to 1e3 and opacities of exactly 0 and 1 during training, a million Gaussians rendered, and a
learning rate far too high. Each ends with finite parameters and finite renders (or a clear error);
never a silent NaN model. Closed-form time bounds and the 64/2048 training steps are in
test_avatar_spacetime.py and test_avatar_trainer.py."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from avatar_helpers import small_config

from stg_node.avatar import AvatarRenderer, Trainer

FPS = 30.0


def _nonfinite(trainer: Trainer) -> list[str]:
    """Names of parameters (table columns, colour MLP, pose corrections) holding NaN or infinity."""
    bad = [n for n in trainer.model.table.names() if not torch.isfinite(trainer.model.table[n]).all()]
    if trainer.model.color_mlp is not None:
        bad += [
            f"mlp.{n}" for n, p in trainer.model.color_mlp.named_parameters() if not torch.isfinite(p).all()
        ]
    if trainer.pose_deltas is not None and not torch.isfinite(trainer.pose_deltas).all():
        bad.append("pose_deltas")
    return bad


def _float32_throughout(trainer: Trainer) -> None:
    for name in trainer.model.table.names():
        assert trainer.model.table[name].dtype == torch.float32, name
    if trainer.model.color_mlp is not None:
        for name, p in trainer.model.color_mlp.named_parameters():
            assert p.dtype == torch.float32, name


def _train(frames, config, steps=None, seed=0, prepare=None):
    trainer = Trainer(config, seed=seed)
    trainer.add_frames(frames)
    if prepare is not None:
        prepare(trainer)
    for _ in range(config.iterations if steps is None else steps):
        trainer.step()
    return trainer


def _person(out, camera_distance=(1.5, 6.0)):
    """Pixels the render covers, after checking its depth is finite and the body where it should be."""
    assert np.isfinite(out.depth).all()
    covered = out.alpha > 0
    if covered.any():
        near, far = camera_distance
        assert near < out.depth[covered].min() and out.depth[covered].max() < far, (
            out.depth[covered].min(),
            out.depth[covered].max(),
        )
    return int(covered.sum())


def _open_motion(trainer: Trainer, t_centers: tuple[float, ...], amplitude_m: float = 0.05) -> None:
    """Make a tenth of the Gaussians dynamic with large motion coefficients centred at ``t_centers``
    (normalised time units), so the polynomials are exercised where the test looks."""
    table = trainer.model.table
    gen = torch.Generator().manual_seed(1)
    rows = torch.randperm(table.num, generator=gen)[: table.num // 10]
    with torch.no_grad():
        table["motion_gate"][rows] = 1.0
        table["motion"][rows] = amplitude_m * torch.randn(table["motion"][rows].shape, generator=gen)
        table["rot_motion"][rows] = 0.1 * torch.randn(table["rot_motion"][rows].shape, generator=gen)
        centres = torch.tensor(t_centers)[torch.arange(rows.numel()) % len(t_centers)]
        table["t_center"][rows] = centres


# --- a sequence spanning 10,000 frames ----------------------------------------------------------
def _spread_over_ten_thousand_frames(frames):
    """Pairs of consecutive frames at the start, middle and end of a 10,000-frame sequence."""
    spread = []
    for k, index in enumerate((0, 1, 4999, 5000, 9998, 9999)):
        f = frames[k % len(frames)]
        spread.append(dataclasses.replace(f, index=index, time=index / FPS))
    return spread


@pytest.fixture(scope="module")
def ten_thousand(tiny_frames):
    frames = _spread_over_ten_thousand_frames(tiny_frames)
    u_end = 9999 / FPS  # the trainer counts time in 1 s units from the first frame

    def prepare(trainer):
        _open_motion(trainer, (0.0, u_end / 2, u_end))

    # Per-Gaussian polynomials: their bounded local time is what is tested at the far ends.
    return frames, _train(frames, small_config(iterations=40, **{"model.motion_basis": 0}), prepare=prepare)


def test_ten_thousand_frames_train_and_render_at_both_ends(ten_thousand):
    frames, trainer = ten_thousand
    assert trainer.skipped_steps == 0 and _nonfinite(trainer) == []
    _float32_throughout(trainer)
    assert int(trainer.model.table.motion_active().sum()) > 0  # the polynomials were in play
    renderer = AvatarRenderer(trainer.model)
    coverage = {}
    for label, t in (("first", 0.0), ("last", 9999 / FPS), ("after", 10_500 / FPS), ("before", -500 / FPS)):
        out = renderer.render(frames[-1].camera, frames[-1].smpl, t, depth=True)
        coverage[label] = _person(out)  # no polynomial blow-up: the body stays where it is
    assert coverage["first"] > 500
    for label in ("last", "after", "before"):
        assert 0.75 < coverage[label] / coverage["first"] < 1.33, coverage


def test_a_stream_of_a_million_frames_still_shows_the_avatar(ten_thousand):
    """Gaussians present at all times (windows >= PERSISTENT_SCALE) get no temporal opacity, so the
    avatar does not fade out of a long stream (it did, after about an hour, before that rule)."""
    frames, trainer = ten_thousand
    out = AvatarRenderer(trainer.model).render(frames[0].camera, frames[0].smpl, 1_000_000 / FPS, depth=True)
    assert _person(out) > 500


# --- very fast motion ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def fast_motion(tmp_path_factory):
    """The dance at 3 frames per second: ten times the articulated motion between consecutive frames
    (elbows swing up to ~170 deg from one frame to the next). 40 frames at 96x96, 32 for training."""
    from stg_node.avatar.data_spec import DataSpec
    from stg_node.avatar.frames import TrainFrame
    from stg_node.data.synth.generate import SynthConfig, generate

    out = tmp_path_factory.mktemp("fast_motion") / "dance_3fps"
    generate(
        SynthConfig(
            out=out, num_frames=40, size=96, num_novel_views=0, supersample=1, motion="dance", fps=3.0
        ),
        progress=False,
    )
    samples = list(DataSpec(str(out), "synthetic", size=96).open("train"))
    return out, samples, [TrainFrame.from_sample(s) for s in samples]


def test_very_fast_motion_trains_with_flow_guided_densification(fast_motion):
    from stg_node.body import load_body_model
    from stg_node.data.synth.true_flow import benchmark_true_flow

    folder, samples, frames = fast_motion
    faces = load_body_model().faces.cpu().numpy()
    moving = []
    for sample in samples[::4]:
        flow = benchmark_true_flow(folder, sample.index, sample.camera, faces, num_frames=40)
        moving.append(flow.magnitude[flow.covered])
    moving = np.concatenate(moving)  # the true image motion of the body, pixels per frame
    assert moving.mean() > 0.04 * 96 and np.percentile(moving, 99) > 0.2 * 96
    trainer = _train(frames, small_config(iterations=60, **{"densify.flow_interval": 10}))
    counts = trainer.densify_counts
    assert "flow_added" in counts  # flow-guided rounds ran on these frames
    assert trainer.skipped_steps == 0 and _nonfinite(trainer) == []
    out = AvatarRenderer(trainer.model).render(frames[3].camera, frames[3].smpl, frames[3].time, depth=True)
    assert _person(out) > 300


# --- extreme poses ---------------------------------------------------------------------------------
def _extreme_poses() -> dict[str, np.ndarray]:
    """(24, 3) axis-angle poses: at both ends of every joint's range, beyond them, exact half and full
    turns (the axis-angle singularities) and random rotations of 5-20 rad."""
    from stg_node.data.synth.joint_limits import JOINT_LIMITS_DEG
    from stg_node.data.synth.rotations import euler_zyx_to_matrix, matrix_to_axis_angle

    def from_euler(deg):
        pose = matrix_to_axis_angle(euler_zyx_to_matrix(np.deg2rad(deg)))
        pose[0] = 0.0  # the global rotation lives in Rh
        return pose

    high, low = JOINT_LIMITS_DEG[..., 1], JOINT_LIMITS_DEG[..., 0]
    beyond = np.clip(high + 0.5 * (high - low) + 20.0, -179.0, 179.0)
    assert (beyond[1:] > high[1:]).all()  # every angle of every joint past its range
    half_turn = np.zeros((24, 3))
    half_turn[1:, 0] = np.pi
    rng = np.random.default_rng(0)
    wild = rng.normal(size=(24, 3))
    wild *= rng.uniform(5.0, 20.0, size=(24, 1)) / np.linalg.norm(wild, axis=1, keepdims=True)
    return {
        "upper limits": from_euler(high),
        "lower limits": from_euler(low),
        "beyond the limits": from_euler(beyond),
        "half turns": half_turn,
        "full turns": 2 * half_turn,
        "5-20 rad": wild,
    }


def test_poses_at_and_beyond_the_joint_limits_train_and_render(tiny_frames):
    poses = _extreme_poses()
    frames = []
    for frame, pose in zip(tiny_frames, poses.values(), strict=False):
        frames.append(
            dataclasses.replace(frame, smpl=dataclasses.replace(frame.smpl, poses=pose.astype(np.float32)))
        )
    frames += tiny_frames[len(frames) :]
    # Pose refinement on: gradients flow through the axis-angle map at its singular points too.
    trainer = _train(frames, small_config(iterations=30, lr_pose=1e-3))
    assert trainer.skipped_steps == 0 and _nonfinite(trainer) == []
    renderer = AvatarRenderer(trainer.model)
    camera, base = tiny_frames[0].camera, tiny_frames[0].smpl
    for name, pose in poses.items():
        smpl = dataclasses.replace(base, poses=pose.astype(np.float32))
        for time_s in (tiny_frames[0].time, None):  # at a training time, and by the novel-pose rule
            assert _person(renderer.render(camera, smpl, time_s, depth=True)) > 100, name


# --- tiny and large images --------------------------------------------------------------------------
@pytest.mark.parametrize("size", [16, 64, 2048])
def test_renders_at_tiny_and_large_sizes_are_finite(tiny_frames, size):
    """Training at 64 and 2048 is tested in test_avatar_trainer.py; this renders a trained model there."""
    from stg_node.data.types import Camera

    trainer = _train(tiny_frames[:4], small_config(iterations=10))
    cam = tiny_frames[0].camera
    k = size / cam.width
    K = np.array(cam.K, np.float64) * np.array([[k], [k], [1.0]])
    scaled = Camera(K, cam.R, cam.t, size, size, cam.name)
    out = AvatarRenderer(trainer.model).render(scaled, tiny_frames[0].smpl, tiny_frames[0].time, depth=True)
    assert out.image.shape == (size, size, 3)
    covered = _person(out)
    assert covered > (0 if size < 32 else 0.02 * size * size)


# --- scales from 1e-6 to 1e3, opacities of exactly 0 and 1 ------------------------------------------
def test_extreme_scales_and_opacities_during_training(tiny_frames):
    """A quarter of the Gaussians at scale 1e-6 m, a quarter at 1e3 m, a quarter at opacity exactly 0
    and a quarter at exactly 1 (logits of -+1e4, which float32's sigmoid maps to 0 and 1), then
    training with densification and pruning."""

    def prepare(trainer):
        table = trainer.model.table
        n = table.num
        quarter = torch.arange(n) % 4
        with torch.no_grad():
            table["log_scales"][quarter == 0] = math.log(1e-6)
            table["log_scales"][quarter == 1] = math.log(1e3)
            table["opacity_logits"][quarter == 2] = -1e4
            table["opacity_logits"][quarter == 3] = 1e4
        opacities = table.opacities()
        assert (opacities[quarter == 2] == 0).all() and (opacities[quarter == 3] == 1).all()
        scales = table.scales()
        assert scales.min() <= 1.01e-6 and scales.max() >= 0.99e3

    trainer = _train(tiny_frames, small_config(iterations=60), prepare=prepare)  # density steps at 40
    assert trainer.skipped_steps == 0 and _nonfinite(trainer) == []
    assert trainer.densify_counts.get("pruned", 0) > 0  # the 1 km Gaussians are gone
    assert float(trainer.model.table.scales().detach().max()) < 1.0  # nothing of the 1 km ones is left
    out = AvatarRenderer(trainer.model).render(
        tiny_frames[0].camera, tiny_frames[0].smpl, tiny_frames[0].time, depth=True
    )
    assert _person(out) > 200


# --- a million Gaussians -----------------------------------------------------------------------------
def test_a_million_gaussian_avatar_renders(tiny_synth):
    from stg_node.avatar.data_spec import DataSpec
    from stg_node.avatar.frames import TrainFrame

    sample = DataSpec(str(tiny_synth), "synthetic", size=256).open("train")[0]
    config = small_config().replace(**{"model.num_gaussians": 1_000_000, "model.max_gaussians": 1_000_000})
    trainer = Trainer(config, seed=0)
    trainer.add_frame(TrainFrame.from_sample(sample))
    assert trainer.model.table.num == 1_000_000
    out = AvatarRenderer(trainer.model).render(sample.camera, sample.smpl, sample.time, depth=True)
    assert out.num_rendered == 1_000_000
    person = sample.mask > 127
    covered = out.alpha > 0
    assert _person(out) > 0.8 * person.sum()
    assert (covered & person).sum() > 0.9 * person.sum()  # the untrained model is the body's surface


# --- a learning rate far too high ---------------------------------------------------------------------
@pytest.mark.parametrize("factor", [10, 1000])
def test_learning_rates_far_too_high_leave_a_finite_model(tiny_frames, factor):
    base = small_config(iterations=60)
    rates = {
        f.name: getattr(base, f.name) * factor
        for f in dataclasses.fields(base)
        if f.name.startswith("lr_") and f.name != "lr_schedule_final"
    }
    trainer = _train(tiny_frames, base.replace(**rates))  # pose refinement (lr_pose) included
    assert _nonfinite(trainer) == []
    assert trainer.model.table.num > 0
    out = AvatarRenderer(trainer.model).render(
        tiny_frames[0].camera, tiny_frames[0].smpl, tiny_frames[0].time, depth=True
    )
    assert np.isfinite(out.depth).all()
