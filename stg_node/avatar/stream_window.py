"""What a bounded trainer keeps of its time-dependent state: the frames it still holds decide.

A trainer whose frame store is bounded (``max_frames``: the online trainer node) sees a stream of
unknown length, but learns only from the frames it holds. The shared motion bases' knots
(motion_basis.py) and the novel-pose time-code index (timecode.py) would otherwise grow with
every second of the stream: about 17 KB of knots per second, three times that with their Adam
moments, and every step's smoothness term and Adam update touch them all. :func:`window_to_frames`
keeps the knots that a held frame reaches (its time through its successor's, which the flow
loss evaluates, widened by the annealed time noise, plus ``KNOT_MARGIN`` knots) and the index
entries of held frames; the Adam moments of the kept knots are sliced with them, never reset.
The store is a reservoir sample (old and new frames stay represented), so the knots kept are
runs around the held frames, not one window: at most about ``(2 + 2 * KNOT_MARGIN + 1)`` knots
per held frame whatever the stream's length. An unbounded store (offline training holds every
frame) never calls this, so offline runs are unchanged. The per-frame exposure gains and
tracked poses (exposure.py, pose_refine.py) are forgotten with their frames too
(:func:`forget_unheld_frames`), as the pose corrections are (``Trainer._compact_pose_slots``).
"""

from __future__ import annotations

import numpy as np
import torch

from stg_node.avatar.frames import FrameStore


def held_spans(store: FrameStore, time_axis, noise_frames: float = 0.0) -> np.ndarray:
    """(F, 2) ``[start, end]`` in time units that each held frame's steps evaluate the motion at."""
    spans = np.zeros((len(store.frames), 2), np.float64)
    for i, stored in enumerate(store.frames):
        t0 = float(stored.frame.time)
        t1 = float(stored.next_time) if stored.next_time is not None else t0
        noise = noise_frames * max(t1 - t0, 1.0 / 30.0)  # the trainer's default interval without a successor
        spans[i] = time_axis(t0 - noise), time_axis(t1 + noise)
    return spans


def window_to_frames(model, optimizer, store: FrameStore, noise_frames: float = 0.0) -> int:
    """Drop the knots and pose-index entries no held frame needs; returns the knots dropped."""
    held_u = np.array([model.time_axis(float(s.frame.time)) for s in store.frames], np.float64)
    model.pose_index.retain(held_u)
    bases = model.motion_bases
    if bases is None or not store.frames:
        return 0
    keep = bases.kept(held_spans(store, model.time_axis, noise_frames))
    if keep.all():
        return 0
    index = torch.as_tensor(np.flatnonzero(keep), device=bases.values.device)
    with torch.no_grad():
        values = bases.values.index_select(1, index)
    old = bases.install(values, bases.knot_ids[keep])
    if optimizer is not None:
        optimizer.select_dense(old, bases.values, 1, index)
    return int((~keep).sum())


def forget_unheld_frames(store: FrameStore, exposure, pose_track) -> None:
    """The per-frame exposure gains and tracked poses of frames the store no longer holds go too,
    once they are twice the store's bound (each cut copies what is kept: amortised)."""
    if len(exposure.slots) <= 2 * store.capacity and len(pose_track.raw) <= 4 * store.capacity + 2:
        return
    held = {stored.frame.index for stored in store.frames}
    if len(exposure.slots) > 2 * store.capacity:
        exposure.retain(held)
    if len(pose_track.raw) > 4 * store.capacity + 2:  # held frames and their neighbours: up to 3x
        pose_track.retain(held)
