"""Opening a finished (or running) training run for rendering: the model, its pose corrections."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from stg_node.avatar.renderer import AvatarRenderer
from stg_node.avatar.run import RunDir
from stg_node.avatar.snapshot import read_snapshot_file


def pose_corrections(msg) -> dict[int, np.ndarray]:
    """Frame number -> (75,) learned correction (72 pose + 3 Th) from a checkpoint, if it has them."""
    arrays = msg.arrays
    if "train.pose_deltas" not in arrays:
        return {}
    frames = np.asarray(arrays["train.pose_frames"]).astype(np.int64)
    deltas = np.asarray(arrays["train.pose_deltas"], np.float32)
    return {int(f): deltas[i] for i, f in enumerate(frames)}


def corrected(smpl, correction: np.ndarray | None):
    """``smpl`` with a learned correction applied (the pose the model was trained on)."""
    if correction is None:
        return smpl
    return dataclasses.replace(
        smpl, poses=smpl.poses + correction[:72].reshape(24, 3), Th=smpl.Th + correction[72:75]
    )


def load_run_renderer(path: Path, *, device="cpu", backend="auto", light=None):
    """(RunDir, AvatarRenderer, pose corrections, summary dict) of a run folder; ``light``: a
    shading.LightSpec the renderer uses (None: the model's learned light)."""
    run = RunDir(Path(path))
    run.read_config()  # a clear error when the folder is not a run
    model_file = run.model_file()
    msg = read_snapshot_file(model_file)
    corrections = pose_corrections(msg)
    if not corrections and run.checkpoint.is_file() and model_file != run.checkpoint:
        corrections = pose_corrections(read_snapshot_file(run.checkpoint))
    renderer = AvatarRenderer.from_snapshot(msg, device=device, backend=backend, light=light)
    summary = json.loads(run.summary.read_text()) if run.summary.is_file() else {}
    return run, renderer, corrections, summary
