"""The trainer on a tiny synthetic capture: it learns, every ablation switch runs, extremes stay finite,
a checkpoint resumes exactly, bad steps are skipped."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
import torch
from avatar_helpers import small_config

from stg_node.avatar import losses as L
from stg_node.avatar.gaussians import MOTION_COLUMNS
from stg_node.avatar.renderer import AvatarRenderer
from stg_node.avatar.trainer import Trainer


def _train(frames, config, steps=None, seed=0, **kw):
    trainer = Trainer(config, seed=seed, **kw)
    trainer.add_frames(frames)
    for _ in range(steps if steps is not None else config.iterations):
        trainer.step()
    return trainer


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)) / 255.0**2
    return -10 * math.log10(max(mse, 1e-12))


def _masked(frame):
    return np.where(frame.mask[..., None] > 127, frame.image, 0).astype(np.uint8)


def test_full_model_overfits_a_tiny_sequence(tiny_frames):
    """300 steps on 10 frames of 128x128: the training views are reproduced to > 25 dB (full image,
    black background), far above what the untrained model gives (about 20 dB)."""
    config = small_config(iterations=300)
    trainer = Trainer(config, seed=0)
    trainer.add_frames(tiny_frames)
    renderer = AvatarRenderer(trainer.model)
    before = np.mean(
        [_psnr(renderer.render(f.camera, f.smpl, f.time).image, _masked(f)) for f in tiny_frames]
    )
    for _ in range(config.iterations):
        result = trainer.step()
        assert not result.skipped
    after = np.mean([_psnr(renderer.render(f.camera, f.smpl, f.time).image, _masked(f)) for f in tiny_frames])
    assert before < 21.0
    assert after > 25.0 and after > before + 5.0, (before, after)
    # stats() against the published snapshot (a second path to the same numbers): row count, the
    # share of rows with any motion coefficient, and the bytes a renderer receives
    stats = trainer.stats()
    snap = trainer.snapshot()
    motion = np.concatenate(
        [
            np.asarray(snap.arrays[f"g.{n}"]).reshape(snap.num_gaussians, -1)
            for n in MOTION_COLUMNS
            if f"g.{n}" in snap.arrays
        ],
        1,
    )
    assert stats["gaussians"] == snap.num_gaussians > 0
    assert stats["active_motion_fraction"] == pytest.approx(float((motion != 0).any(axis=1).mean()))
    assert stats["model_mb"] == pytest.approx(sum(a.nbytes for a in snap.arrays.values()) / 1e6)


@pytest.mark.parametrize(
    "changes, absent",
    [
        ({"model.spacetime": False}, {"motion", "rot_motion", "t_center", "t_log_scale"}),
        ({"densify.flow_guided": False}, set()),
        ({"model.color": "sh", "model.sh_degree": 2}, {"features"}),
        (
            {"model.motion_order": 0, "model.rotation_order": 0, "model.motion_basis": 0},
            {"motion", "rot_motion"},
        ),
        ({"model.motion_order": 3, "model.motion_basis": 0}, {"motion_coef"}),
        ({"model.learn_skin_weights": False, "model.skin_init": "nearest"}, {"skin_delta"}),
    ],
)
def test_every_ablation_switch_trains(tiny_frames, changes, absent):
    trainer = _train(tiny_frames, small_config(**changes, iterations=25))
    names = set(trainer.model.table.names())
    assert not (absent & names)
    if changes.get("model.color") == "sh":
        assert trainer.model.color_mlp is None and "sh" in names
    if changes.get("model.motion_order") == 3:
        assert trainer.model.table["motion"].shape[1] == 3
    for name in names:
        assert torch.isfinite(trainer.model.table[name]).all(), name
    assert trainer.skipped_steps == 0


@pytest.mark.parametrize("size", [64, 2048])
def test_tiny_and_large_images_train_without_nan(tiny_synth, size):
    from stg_node.avatar.data_spec import DataSpec
    from stg_node.avatar.frames import TrainFrame

    ds = DataSpec(str(tiny_synth), "synthetic", size=size).open("train")
    frames = [TrainFrame.from_sample(ds[i]) for i in (0, 1)]
    trainer = _train(frames, small_config(iterations=3), steps=3)
    assert trainer.skipped_steps == 0
    for name in trainer.model.table.names():
        assert torch.isfinite(trainer.model.table[name]).all(), name


def test_same_seed_same_model_and_other_seed_another(tiny_frames):
    config = small_config(iterations=30)
    a = _train(tiny_frames[:4], config, seed=7)
    b = _train(tiny_frames[:4], config, seed=7)
    c = _train(tiny_frames[:4], config, seed=8)
    for name in a.model.table.names():
        assert torch.equal(a.model.table[name], b.model.table[name]), name
    assert not torch.equal(a.model.table["means"], c.model.table["means"])


def test_resumed_checkpoint_continues_exactly_like_the_uninterrupted_run(tiny_frames, tmp_path):
    """Densification (from step 20) and the per-step randomness included: 25 steps, save, load,
    25 more equals 50 steps straight."""
    config = small_config(iterations=50, lr_pose=1e-4)
    straight = _train(tiny_frames, config)
    first = _train(tiny_frames, config, steps=25)
    first.notes = {"wall_s": 12.5}
    path = first.save(tmp_path / "ck.stgsnap")
    resumed = Trainer.load(path)
    # The caller's notes and the isometry loss's neighbour graph come back as they were saved.
    assert resumed.notes == {"wall_s": 12.5}
    assert first.isometry.neighbours is not None
    assert torch.equal(resumed.isometry.neighbours, first.isometry.neighbours)
    resumed.add_frames(tiny_frames)
    assert resumed.iteration == 25
    for _ in range(25):
        resumed.step()
    assert straight.model.table.num == resumed.model.table.num
    for name in straight.model.table.names():
        assert torch.equal(straight.model.table[name], resumed.model.table[name]), name
    for (k, v), (k2, v2) in zip(
        straight.model.color_mlp.state_dict().items(),
        resumed.model.color_mlp.state_dict().items(),
        strict=True,
    ):
        assert k == k2 and torch.equal(v, v2), k
    assert torch.equal(straight.pose_deltas, resumed.pose_deltas)
    # The densification strategy's state is a dict the trainer owns, stored as it is.
    assert straight.densify_state.keys() == resumed.densify_state.keys()
    for key, value in straight.densify_state.items():
        assert torch.equal(value, resumed.densify_state[key]), key
    assert straight.densify_counts == resumed.densify_counts and "flow_added" in straight.densify_counts


def test_a_non_finite_step_is_skipped_and_never_written(tiny_frames, monkeypatch, caplog):
    trainer = _train(tiny_frames[:3], small_config(iterations=10), steps=2)
    before = {n: trainer.model.table[n].detach().clone() for n in trainer.model.table.names()}
    real = L.photometric

    def poisoned(render, target, w):
        l1, dssim = real(render, target, w)
        return l1 * float("nan"), dssim

    monkeypatch.setattr(L, "photometric", poisoned)
    with caplog.at_level(logging.WARNING, logger="stg_node.avatar.trainer"):
        result = trainer.step()
    assert result.skipped and math.isnan(result.loss)
    assert "non-finite" in caplog.text
    for name, value in before.items():
        assert torch.equal(trainer.model.table[name], value), name
    monkeypatch.setattr(L, "photometric", real)
    assert not trainer.step().skipped
    assert trainer.skipped_steps == 1


def test_bounded_store_keeps_memory_flat(tiny_frames):
    trainer = Trainer(small_config(max_frames=4), seed=0)
    for _ in range(3):
        trainer.add_frames(tiny_frames)
    assert len(trainer.store) == 4 and trainer.store.seen == 3 * len(tiny_frames)
    for _ in range(3):
        assert not trainer.step().skipped


def test_bad_frames_are_refused_with_a_clear_error(tiny_frames):
    import dataclasses

    trainer = Trainer(small_config(), seed=0)
    frame = tiny_frames[0]
    with pytest.raises(ValueError, match="image must be"):
        trainer.add_frame(dataclasses.replace(frame, image=frame.image[:10]))
    with pytest.raises(ValueError, match="time"):
        trainer.add_frame(dataclasses.replace(frame, time=float("nan")))
    with pytest.raises(RuntimeError, match="add_frame"):
        trainer.step()


def test_read_only_frames_from_the_bus_train_without_warnings(tiny_frames):
    """Frames decoded from bus messages are read-only numpy views; the trainer copies what it keeps."""
    import dataclasses
    import warnings

    from stg_node.body.params import SmplParams

    def frozen(a):
        a = np.array(a)
        a.setflags(write=False)
        return a

    frames = []
    for f in tiny_frames[:3]:
        smpl = SmplParams(frozen(f.smpl.poses), frozen(f.smpl.Rh), frozen(f.smpl.Th), frozen(f.smpl.betas))
        frames.append(dataclasses.replace(f, image=frozen(f.image), mask=None, smpl=smpl))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        trainer = _train(frames, small_config(iterations=3), steps=3)
    assert trainer.skipped_steps == 0


def test_a_trainer_node_respawned_from_its_checkpoint_keeps_its_frame_bound(
    tiny_frames, tmp_path, monkeypatch
):
    """The real trainer through the trainer node's own resume path (TrainerAdapter.load ->
    checkpoint.load): the frame store's bound (max_frames) lives in the config the checkpoint keeps,
    so a respawned node stays bounded on an endless stream instead of growing without limit; and
    its iteration and wall time come back from that one file."""
    import shutil
    import tempfile

    from stg_node.bus import BusConfig
    from stg_node.nodes.params import parse_params
    from stg_node.nodes.trainer import TrainerNode, TrainerParams

    folder = tempfile.mkdtemp(prefix="stgt-")  # a short ipc path; no broker needed to set up
    params = parse_params(
        TrainerParams, {"max_frames": 3, "checkpoint_dir": str(tmp_path), "checkpoint_every_s": 0}
    )

    def node() -> TrainerNode:
        made = TrainerNode("trainer", params, BusConfig(url=f"ipc://{folder}/bus"), heartbeat_s=0)
        made.setup()
        return made

    def feed(trainer, frames) -> None:
        for f in frames:
            trainer.add_frame(
                index=f.index, time=f.time, image=f.image, mask=f.mask, camera=f.camera, smpl=f.smpl
            )

    monkeypatch.delenv("STG_RESPAWN", raising=False)
    first = node()
    try:
        assert first.trainer.max_frames == 3 and first.resumed_from is None
        feed(first.trainer, tiny_frames[:4])
        for _ in range(2):
            first.iteration = first.trainer.step().iteration
        first._save_checkpoint()
    finally:
        first.bus.close()
    monkeypatch.setenv("STG_RESPAWN", "1")  # what stg-launch sets on a respawn
    second = node()
    try:
        assert second.resumed_from is not None and second.iteration == 2
        assert second.elapsed_before > 0
        assert second.trainer.max_frames == 3
        feed(second.trainer, tiny_frames * 2)  # a stream longer than the bound
        store = second.trainer._trainer.store
        assert len(store) == 3 and store.seen == 2 * len(tiny_frames)
        assert not second.trainer.step().skipped
    finally:
        second.bus.close()
        shutil.rmtree(folder, ignore_errors=True)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_the_finiteness_check_finds_one_bad_gradient_and_passes_huge_finite_ones(tiny_frames, bad):
    trainer = _train(tiny_frames[:3], small_config(iterations=10), steps=1)
    params = [p for group in trainer.optimizer.groups() for p in group["params"]]
    for p in params:
        p.grad = torch.full_like(p, 1e38)  # finite, though its square overflows
    assert trainer._grads_finite()
    last = params[-1]
    last.grad.view(-1)[last.numel() // 2] = bad
    assert not trainer._grads_finite()


def test_flow_loss_matches_a_per_pixel_charbonnier_and_ignores_invalid_nan_flow():
    gen = torch.Generator().manual_seed(3)
    h, w = 9, 7
    rendered = torch.randn(h, w, 2, generator=gen, dtype=torch.float64, requires_grad=True)
    alpha = torch.rand(h, w, 1, generator=gen, dtype=torch.float64, requires_grad=True)
    flow = torch.randn(h, w, 2, generator=gen, dtype=torch.float64)
    valid = torch.rand(h, w, generator=gen) > 0.3
    flow[~valid] = float("nan")  # what an invalid flow pixel may hold
    loss = L.flow_loss(rendered, alpha, flow, valid)
    g_rendered, g_alpha = torch.autograd.grad(loss, (rendered, alpha))
    # the definition, pixel by pixel: Charbonnier distance of alpha-normalised rendered flow
    terms = []
    for y in range(h):
        for x in range(w):
            if valid[y, x] and alpha[y, x, 0] > 0.5:
                d = rendered[y, x] / alpha[y, x, 0] - flow[y, x]
                terms.append(torch.sqrt((d * d).sum() + L.CHARBONNIER_EPS**2))
    want = torch.stack(terms).mean() - L.CHARBONNIER_EPS
    w_rendered, w_alpha = torch.autograd.grad(want, (rendered, alpha))
    assert len(terms) > 10 and float(loss.detach()) == pytest.approx(float(want.detach()), rel=1e-12)
    assert torch.isfinite(g_rendered).all() and torch.isfinite(g_alpha).all()
    torch.testing.assert_close(g_rendered, w_rendered, rtol=1e-10, atol=1e-14)
    torch.testing.assert_close(g_alpha, w_alpha, rtol=1e-10, atol=1e-14)
    nothing = torch.zeros(h, w, dtype=torch.bool)
    assert float(L.flow_loss(rendered, alpha, flow, nothing)) == 0.0
