"""Checkpoints: the whole trainer in one GaussianSnapshot file, so a killed run resumes exactly.

What the model needs is the published snapshot (snapshot.py); a checkpoint adds, as ``train.*``
arrays and meta: the Adam moments of every column and dense module, the densification
strategy's state dict, the isometry loss's state, the per-frame pose corrections, the
adaptive-weight averages, the counters, the caller's ``notes``, the per-frame exposure gains,
the colours carried by the colour MLP's turns, the training cameras' statistics columns (a rig
that reconnects in another order keeps each camera's column), and the TrainConfig (the frame store's bound
``max_frames`` with it) with what the trainer decided about the non-rigid part (JSON bytes) and
the subject's betas (to rebuild the canonical mesh). Frames are not saved: ``stg-train --resume``
re-reads them from the dataset, the online trainer from the stream.
Because every random choice of step k is a function of (seed, k), a run resumed at checkpoint k
is the uninterrupted run.

One direction: the trainer gathers its state into a :class:`TrainingState` and hands it to
:func:`save`; :func:`load` returns one that the trainer rebuilds itself from. Nothing here
knows the Trainer.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from stg_node.avatar.config import TrainConfig
from stg_node.avatar.model import AvatarModel
from stg_node.avatar.snapshot import (
    array_to_json,
    json_to_array,
    model_from_snapshot,
    read_snapshot_file,
    to_snapshot,
    write_snapshot_file,
)

STATE_KEYS = ("exp_avg", "exp_avg_sq")
AdamState = dict[str, torch.Tensor]  # step, exp_avg, exp_avg_sq


@dataclass
class TrainingState:
    """Everything a trainer needs to continue exactly (besides its frames)."""

    model: AvatarModel
    config: TrainConfig
    body_model: str  # what finds the body again: a path, or "open"
    seed: int
    betas: torch.Tensor  # (1, S)
    iteration: int = 0
    train_seconds: float = 0.0
    skipped_steps: int = 0
    frames_seen: int = 0
    model_version: int = 0
    table_adam: dict[str, AdamState] = field(default_factory=dict)  # column -> Adam state
    dense_adam: dict[str, AdamState] = field(default_factory=dict)  # "group.i" -> Adam state
    pose_deltas: torch.Tensor | None = None  # (slots, 75)
    pose_frames: list[int] = field(default_factory=list)  # frame number of each slot
    densify: dict[str, torch.Tensor] = field(default_factory=dict)  # the strategy's state dict
    loss_ema: dict[str, float] = field(default_factory=dict)
    nonrigid: dict = field(default_factory=dict)  # the trainer's decision about the non-rigid part
    isometry: dict[str, torch.Tensor] = field(default_factory=dict)  # the isometry loss's state arrays
    notes: dict[str, float] = field(default_factory=dict)  # the caller's figures (e.g. wall time)
    exposure: dict[str, np.ndarray] = field(default_factory=dict)  # per-frame exposure gains (exposure.py)
    color_turns: dict[str, np.ndarray] = field(default_factory=dict)  # carried colours (color_cache.py)
    camera_slots: dict[str, int] = field(default_factory=dict)  # training camera name -> statistics column


def _np(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to("cpu", torch.float32).numpy())


def _adam_arrays(prefix: str, states: dict[str, AdamState], arrays: dict, meta: dict) -> None:
    for name, state in states.items():
        for key in STATE_KEYS:
            arrays[f"{prefix}.{name}.{key}"] = _np(state[key])
        meta[f"{prefix}.{name}.step"] = float(state["step"])


def _adam_states(prefix: str, arrays: dict, meta: dict, tensor) -> dict[str, AdamState]:
    out = {}
    for key in meta:
        if key.startswith(prefix + ".") and key.endswith(".step"):
            name = key[len(prefix) + 1 : -len(".step")]
            out[name] = {
                "step": torch.tensor(meta[key]),
                **{k: tensor(f"{prefix}.{name}.{k}") for k in STATE_KEYS},
            }
    return out


def save(path: str | Path, state: TrainingState) -> Path:
    """Write ``state`` as one snapshot file (atomic: temporary file, fsync, rename)."""
    arrays: dict[str, np.ndarray] = {}
    meta: dict[str, float] = {
        "train.iteration": float(state.iteration),
        "train.seconds": float(state.train_seconds),
        "train.skipped": float(state.skipped_steps),
        "train.seed": float(state.seed),
        "train.frames_seen": float(state.frames_seen),
    }
    arrays["train.config_json"] = json_to_array(
        {
            "config": state.config.to_dict(),
            "body_model": state.body_model,
            "nonrigid": state.nonrigid,
            "camera_slots": state.camera_slots,
        }
    )
    arrays["train.betas"] = _np(state.betas).reshape(-1)
    _adam_arrays("train.adam", state.table_adam, arrays, meta)
    _adam_arrays("train.dense", state.dense_adam, arrays, meta)
    if state.pose_deltas is not None:
        arrays["train.pose_deltas"] = _np(state.pose_deltas)
        arrays["train.pose_frames"] = np.asarray(state.pose_frames, np.float32)
    for name, value in state.exposure.items():
        arrays[f"train.exposure.{name}"] = value
    for name, value in state.color_turns.items():
        arrays[f"train.color_turns.{name}"] = value
    for name, value in state.densify.items():
        arrays[f"train.densify.{name}"] = _np(value)
    for name, value in state.loss_ema.items():
        meta[f"train.ema.{name}"] = float(value)
    for name, value in state.isometry.items():
        arrays[f"train.isometry.{name}"] = _np(value)
    for name, value in state.notes.items():
        meta[f"train.notes.{name}"] = float(value)
    msg = to_snapshot(
        state.model,
        iteration=state.iteration,
        model_version=state.model_version,
        extra_arrays=arrays,
        extra_meta=meta,
    )
    return write_snapshot_file(path, msg)


def load(path: str | Path, *, device="cpu") -> TrainingState:
    """The training state in the checkpoint at ``path`` (tensors on ``device``)."""
    msg = read_snapshot_file(path)
    arrays, meta = msg.arrays, msg.meta
    if "train.config_json" not in arrays:
        raise ValueError(f"{path} is a published snapshot, not a training checkpoint (no train.* state)")
    stored = array_to_json(arrays["train.config_json"])
    dev = torch.device(device)

    def tensor(name):
        return torch.as_tensor(np.array(arrays[name], np.float32), device=dev)

    densify = {
        name[len("train.densify.") :]: tensor(name) for name in arrays if name.startswith("train.densify.")
    }
    # Checkpoints written before the strategy kept one state dict held these as meta.
    if "initial_parts" in densify:
        densify["initial_part_counts"] = densify.pop("initial_parts")
    for key, value in meta.items():
        if key == "train.densify.steps_seen":
            densify["steps_seen"] = torch.tensor([float(value)], device=dev)
        elif key.startswith("train.densify.count."):
            densify["count." + key[len("train.densify.count.") :]] = torch.tensor([float(value)], device=dev)
    if "alive_count" not in densify and "vis_count" in densify and "steps_seen" in densify:
        # Written before each row's own step count was kept: every row there for the whole interval.
        densify["alive_count"] = torch.full_like(densify["vis_count"], float(densify["steps_seen"]))
    pose_frames = []
    if "train.pose_frames" in arrays:
        pose_frames = [int(f) for f in np.asarray(arrays["train.pose_frames"])]
    return TrainingState(
        model=model_from_snapshot(msg, device=dev),
        config=TrainConfig.from_dict(stored["config"]),
        body_model=stored.get("body_model"),
        seed=int(meta["train.seed"]),
        betas=tensor("train.betas")[None],
        iteration=int(meta["train.iteration"]),
        train_seconds=float(meta["train.seconds"]),
        skipped_steps=int(meta["train.skipped"]),
        frames_seen=int(meta.get("train.frames_seen", 0)),
        model_version=int(msg.model_version),
        table_adam=_adam_states("train.adam", arrays, meta, tensor),
        dense_adam=_adam_states("train.dense", arrays, meta, tensor),
        pose_deltas=tensor("train.pose_deltas") if "train.pose_deltas" in arrays else None,
        pose_frames=pose_frames,
        densify=densify,
        loss_ema={k[len("train.ema.") :]: float(v) for k, v in meta.items() if k.startswith("train.ema.")},
        nonrigid=dict(stored.get("nonrigid") or {}),
        isometry={k[len("train.isometry.") :]: tensor(k) for k in arrays if k.startswith("train.isometry.")},
        notes={k[len("train.notes.") :]: float(v) for k, v in meta.items() if k.startswith("train.notes.")},
        exposure={
            k[len("train.exposure.") :]: v for k, v in arrays.items() if k.startswith("train.exposure.")
        },
        color_turns={
            k[len("train.color_turns.") :]: v for k, v in arrays.items() if k.startswith("train.color_turns.")
        },
        camera_slots={str(k): int(v) for k, v in (stored.get("camera_slots") or {}).items()},
    )
