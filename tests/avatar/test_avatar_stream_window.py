"""A bounded trainer keeps only the knots and pose-index entries its held frames need
(stream_window.py): an endless stream stays bounded, and what is kept is unchanged."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from avatar_helpers import small_config

from stg_node.avatar.motion_basis import KNOT_MARGIN, MotionBases
from stg_node.avatar.snapshot import model_from_snapshot, to_snapshot
from stg_node.avatar.trainer import Trainer

INTERVAL_S = 0.2  # three knots (1/15 s) between frames: a short stream spans many knots


def _stream(tiny_frames, count: int, start: int = 0):
    """``count`` frames of a stream: the tiny subject's frames over and over, one every INTERVAL_S."""
    n = len(tiny_frames)
    return [
        dataclasses.replace(tiny_frames[i % n], index=i, time=i * INTERVAL_S)
        for i in range(start, start + count)
    ]


def _held_u(trainer) -> np.ndarray:
    return np.array(sorted(trainer.model.time_axis(s.frame.time) for s in trainer.store.frames))


def _last_knot(trainer, time_s: float) -> int:
    """The knot at or after ``time_s``: where the bases' growth reaches."""
    return math.ceil(trainer.model.time_axis(time_s) / trainer.model.motion_bases.knot_units)


def _reference(values: torch.Tensor, knot_units: float, u: float) -> torch.Tensor:
    """The untrimmed bases at ``u``, written out: linear between knots floor(x) and floor(x) + 1."""
    x = min(max(u / knot_units, 0.0), values.shape[1] - 1.0)
    k = min(math.floor(x), values.shape[1] - 2)
    f = x - k
    return (1 - f) * values[:, k] + f * values[:, k + 1]


def test_a_stream_longer_than_the_store_keeps_knots_and_pose_index_bounded(tiny_frames):
    max_frames = 4
    trainer = Trainer(small_config(max_frames=max_frames), seed=0)
    per_frame = math.ceil(INTERVAL_S * 15) + 2 * KNOT_MARGIN + 2  # a frame's reach to its successor
    bound = max_frames * per_frame + 2
    most = 0
    for frame in _stream(tiny_frames, 60):
        trainer.add_frame(frame)
        bases = trainer.model.motion_bases
        most = max(most, bases.knots)
        held = _held_u(trainer)
        # every held frame still has the two knots around it
        grid = held / bases.knot_units
        assert np.isin(np.floor(grid + 1e-9).astype(int), bases.knot_ids).all()
        assert np.isin(np.ceil(grid - 1e-9).astype(int), bases.knot_ids).all()
        # the pose index holds the held frames, nothing else
        assert np.allclose(np.sort(trainer.model.pose_index.times), held, atol=1e-5)
    untrimmed = _last_knot(trainer, 59 * INTERVAL_S) + 1
    assert untrimmed >= 178 and most <= bound < untrimmed / 3
    assert trainer.model.motion_bases.knot_ids[-1] == untrimmed - 1  # grown to the stream's end
    assert len(trainer.store) == max_frames


def test_an_unbounded_store_keeps_every_knot(tiny_frames):
    trainer = Trainer(small_config(), seed=0)
    trainer.add_frames(_stream(tiny_frames, 8))
    bases = trainer.model.motion_bases
    assert (
        np.array_equal(bases.knot_ids, np.arange(bases.knots))
        and bases.knots == _last_knot(trainer, 7 * INTERVAL_S) + 1
    )
    assert len(trainer.model.pose_index) == 8


def test_offsets_inside_the_window_are_unchanged_by_a_trim():
    gen = torch.Generator().manual_seed(3)
    ku = 0.5
    values = torch.randn(3, 40, 3, 4, generator=gen)
    bases = MotionBases(3, ku, values=values)
    spans = np.array([[4.1, 4.6], [11.0, 11.2], [15.3, 15.3]])  # time units, a reservoir's scattered frames
    keep = bases.kept(spans)
    assert keep[-1] and not keep.all()
    bases.install(values[:, torch.as_tensor(np.flatnonzero(keep))], bases.knot_ids[keep])
    assert bases.first_knot == math.floor(4.1 / ku) - KNOT_MARGIN and not bases.contiguous
    for start, end in spans:  # inside each kept run: the untrimmed motion, value and derivative
        for u in np.linspace(start - KNOT_MARGIN * ku, end + KNOT_MARGIN * ku, 23):
            assert torch.allclose(bases.at(u), _reference(values, ku, u), atol=1e-6), u
            x = u / ku
            if abs(x - round(x)) > 1e-6:
                k = math.floor(x)
                slope = (values[:, k + 1] - values[:, k]) / ku
                assert torch.allclose(bases.derivative(u), slope, atol=1e-5), u
    first, last = bases.knot_ids[0], bases.knot_ids[-1]
    assert torch.equal(bases.at(0.0), values[:, first])  # before the first held knot: its value
    assert torch.equal(bases.at(100.0), values[:, last])  # after the last: the last one's
    # in a gap between two runs: linear between the runs' facing knots
    a = int(bases.knot_ids[np.searchsorted(bases.knot_ids, 16) - 1])
    b = int(bases.knot_ids[np.searchsorted(bases.knot_ids, 16)])
    u = 0.5 * (a + b) * ku
    assert torch.allclose(bases.at(u), 0.5 * (values[:, a] + values[:, b]), atol=1e-6)
    # the smoothness term: second differences within runs of consecutive knots, none across a gap
    ids = bases.knot_ids
    triples = [k for k in range(len(ids) - 2) if ids[k + 2] - ids[k] == 2]
    assert 0 < len(triples) < len(ids) - 2
    second = torch.stack(
        [values[:, ids[k]] - 2 * values[:, ids[k] + 1] + values[:, ids[k] + 2] for k in triples], 1
    )
    expected = 100.0 * (second[..., :3].abs().sum((-1, -2)) + second[..., 3].abs().sum(-1)).mean()
    assert torch.allclose(bases.roughness(), expected)


def test_adam_moments_of_kept_knots_survive_a_trim(tiny_frames):
    trainer = Trainer(small_config(max_frames=3), seed=0)
    trainer.add_frames(_stream(tiny_frames, 6))
    bases = trainer.model.motion_bases
    bases.values.grad = torch.randn(bases.values.shape, generator=torch.Generator().manual_seed(0))
    trainer.optimizer.dense.step()
    for frame in _stream(tiny_frames, 30, start=6):  # until a frame drops knots and keeps others
        before_ids = bases.knot_ids.copy()
        before = {k: v.clone() for k, v in trainer.optimizer.dense.state[bases.values].items()}
        before_values = bases.values.detach().clone()
        trainer.add_frame(frame)
        bases = trainer.model.motion_bases
        dropped = ~np.isin(before_ids, bases.knot_ids)
        if dropped.any() and not dropped.all():
            break
    else:
        pytest.fail("no trim kept some knots")
    state = trainer.optimizer.dense.state[bases.values]
    common, old_at, new_at = np.intersect1d(before_ids, bases.knot_ids, return_indices=True)
    grown = ~np.isin(bases.knot_ids, before_ids)
    for key in ("exp_avg", "exp_avg_sq"):
        assert state[key].shape == bases.values.shape
        assert torch.equal(state[key][:, new_at], before[key][:, old_at]), key
        assert float(before[key][:, old_at].abs().sum()) > 0
        assert float(state[key][:, grown].abs().sum()) == 0.0  # knots grown since start at zero
    assert torch.equal(state["step"], before["step"])
    assert torch.equal(bases.values.detach()[:, new_at], before_values[:, old_at])
    trainer.step()  # the optimiser steps the new parameter
    assert trainer.optimizer.dense.state[trainer.model.motion_bases.values]["step"] == before["step"] + 1


def test_snapshot_and_checkpoint_keep_the_knot_window(tiny_frames, tmp_path):
    trainer = Trainer(small_config(max_frames=3), seed=0)
    trainer.add_frames(_stream(tiny_frames, 12))
    bases = trainer.model.motion_bases
    with torch.no_grad():
        bases.values.copy_(torch.randn(bases.values.shape, generator=torch.Generator().manual_seed(1)))
    assert bases.first_knot > 0
    msg = to_snapshot(trainer.model)
    assert msg.meta["motion.first_knot"] == bases.first_knot
    model = model_from_snapshot(msg)
    assert np.array_equal(model.motion_bases.knot_ids, bases.knot_ids)
    assert np.allclose(model.pose_index.times, trainer.model.pose_index.times)
    for u in _held_u(trainer):
        assert torch.equal(model.motion_bases.at(u), bases.at(u))
    trainer.step()
    path = trainer.save(tmp_path / "ck.stgsnap")
    resumed = Trainer.load(path)
    r = resumed.model.motion_bases
    assert np.array_equal(r.knot_ids, trainer.model.motion_bases.knot_ids)
    assert torch.equal(r.values, trainer.model.motion_bases.values)
    state = resumed.optimizer.dense.state[r.values]
    original = trainer.optimizer.dense.state[trainer.model.motion_bases.values]
    assert torch.equal(state["exp_avg_sq"], original["exp_avg_sq"])
    resumed.add_frames(_stream(tiny_frames, 3, start=12))  # the stream goes on
    assert resumed.model.motion_bases.knot_ids[-1] == _last_knot(resumed, 14 * INTERVAL_S)
    resumed.step()


def test_a_snapshot_from_before_windowed_knots_loads_with_its_knots_from_zero(tiny_frames):
    trainer = Trainer(small_config(), seed=0)
    trainer.add_frames(_stream(tiny_frames, 3))
    msg = to_snapshot(trainer.model)
    old = dataclasses.replace(
        msg,
        meta={k: v for k, v in msg.meta.items() if k != "motion.first_knot"},
        arrays={k: v for k, v in msg.arrays.items() if k != "motion.knot_ids"},
    )
    model = model_from_snapshot(old)
    assert np.array_equal(model.motion_bases.knot_ids, np.arange(trainer.model.motion_bases.knots))
    bad = dataclasses.replace(msg, meta={**msg.meta, "motion.first_knot": -2.0})
    with pytest.raises(ValueError, match="first_knot"):
        model_from_snapshot(bad)


def test_pose_corrections_of_held_frames_survive_and_stay_as_many_as_the_store(tiny_frames):
    trainer = Trainer(small_config(max_frames=4), seed=0)
    trainer.add_frames(_stream(tiny_frames, 40))
    assert trainer.pose_deltas.shape[0] == 64  # the first block of slots
    deltas = trainer.pose_deltas
    deltas.grad = torch.randn(deltas.shape, generator=torch.Generator().manual_seed(2))
    deltas.grad[len(trainer.pose_slots) :] = 0  # slots not given out yet get no gradient in training either
    trainer.optimizer.dense.step()  # moments and values for every slot
    compactions = checked = 0
    for frame in _stream(tiny_frames, 160, start=40):  # 200 frames: without compaction 256 slots
        deltas = trainer.pose_deltas
        moments = trainer.optimizer.dense.state[deltas]["exp_avg"]
        before = {
            f: (deltas.detach()[slot].clone(), moments[slot].clone())
            for f, slot in trainer.pose_slots.items()
        }
        trainer.add_frame(frame)
        deltas = trainer.pose_deltas
        assert deltas.shape[0] == 64
        compactions += len(trainer.pose_slots) <= len(before)  # slots of frames no longer held freed
        state = trainer.optimizer.dense.state[deltas]["exp_avg"]
        for f, slot in trainer.pose_slots.items():
            if f in before:  # kept: its correction and its moments, wherever its slot went
                assert torch.equal(deltas.detach()[slot], before[f][0]) and torch.equal(
                    state[slot], before[f][1]
                )
                checked += float(before[f][1].abs().sum()) > 0
            else:  # the frame just added: a fresh correction
                assert f == frame.index and float(deltas.detach()[slot].abs().sum()) == 0.0
        held = {s.frame.index for s in trainer.store.frames}
        assert held <= set(trainer.pose_slots)
    assert compactions > 0 and checked > 0
    trainer.step()


def test_exposure_gains_and_tracked_poses_follow_the_held_frames(tiny_frames):
    trainer = Trainer(small_config(max_frames=4, lr_exposure=0.5, **{"loss.pose_smooth": 1e-3}), seed=0)
    assert trainer.exposure.enabled
    gains_seen: dict[int, torch.Tensor] = {}
    for frame in _stream(tiny_frames, 120):
        trainer.add_frame(frame)
        exposure = trainer.exposure
        if frame.index not in exposure.slots:  # the reservoir did not keep it, and a cut came
            assert frame.index not in {s.frame.index for s in trainer.store.frames}
            continue
        row = exposure.slots[frame.index]
        exposure.gains[row] = 0.01 * (frame.index % 7 + 1)  # a gain to recognise each frame by
        exposure.steps[row] = frame.index + 1  # and a draw count
        gains_seen[frame.index] = (exposure.gains[row].clone(), int(exposure.steps[row]))
        held = {s.frame.index for s in trainer.store.frames}
        assert held <= set(exposure.slots) and len(exposure.slots) <= 2 * 4 + 1
        for f, r in exposure.slots.items():  # every row (gains and draw count) still belongs to its frame
            assert torch.equal(exposure.gains[r], gains_seen[f][0])
            assert int(exposure.steps[r]) == gains_seen[f][1]
        track = trainer.pose_track.raw
        assert len(track) <= 4 * 4 + 3
        assert all(f in track for f in held)
        assert all(f - 1 in track for f in held if f > 0)  # the neighbours a second difference needs
    trainer.step()  # consistent shapes after the cuts
    assert len(exposure.gains) == len(exposure.steps) == len(exposure.slots)


def test_growing_the_pose_slots_keeps_every_dense_moment(tiny_frames):
    """An unbounded stream doubles the pose corrections' slots; the colour MLP, light and every
    other dense module keep their Adam moments, and the held corrections keep theirs."""
    trainer = Trainer(small_config(), seed=0)  # max_frames 0: every frame kept
    trainer.add_frames(_stream(tiny_frames, 64))
    assert trainer.pose_deltas.shape[0] == 64
    dense = trainer.optimizer.dense
    gen = torch.Generator().manual_seed(3)
    for group in dense.param_groups:
        for p in group["params"]:
            p.grad = torch.randn(p.shape, generator=gen)
    dense.step()
    before = {
        (group["name"], i): {k: v.clone() for k, v in dense.state[p].items()}
        for group in dense.param_groups
        for i, p in enumerate(group["params"])
    }
    assert len(before) > 1  # the pose corrections and at least the colour MLP
    trainer.add_frame(_stream(tiny_frames, 1, start=64)[0])  # slot 65: the block doubles
    assert trainer.pose_deltas.shape[0] == 128
    dense = trainer.optimizer.dense
    for group in dense.param_groups:
        for i, p in enumerate(group["params"]):
            old = before[(group["name"], i)]
            state = dense.state[p]
            assert float(state["step"]) == float(old["step"])
            for key in ("exp_avg", "exp_avg_sq"):
                value = state[key]
                grown = tuple(slice(0, n) for n in old[key].shape)
                assert torch.equal(value[grown], old[key]), (group["name"], key)
                rest = value.clone()
                rest[grown] = 0
                assert not rest.any()  # the new slots start at zero
