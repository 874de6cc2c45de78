"""Checkpoints: the whole trainer in one GaussianSnapshot file, so a killed run resumes exactly.

What the model needs is the published snapshot (snapshot.py); a checkpoint adds, as ``train.*``
arrays and meta: the Adam moments of every column and dense module, the densification
statistics, the per-frame pose corrections, the adaptive-weight averages, the counters, and
the TrainConfig (JSON bytes, the frame store's bound ``max_frames`` with it), the subject's betas
(to rebuild the canonical mesh) and the caller's ``notes``. Frames are not
saved: ``stg-train --resume`` re-reads them from the dataset, the online trainer from the
stream. Because every random choice of step k is a function of (seed, k), a run resumed at
checkpoint k is the uninterrupted run.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from stg_node.avatar.config import TrainConfig
from stg_node.avatar.snapshot import (
    array_to_json,
    json_to_array,
    model_from_snapshot,
    read_snapshot_file,
    to_snapshot,
    write_snapshot_file,
)

STATE_KEYS = ("exp_avg", "exp_avg_sq")


def _np(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to("cpu", torch.float32).numpy())


def training_state(trainer) -> tuple[dict, dict]:
    arrays: dict[str, np.ndarray] = {}
    meta: dict[str, float] = {
        "train.iteration": float(trainer.iteration),
        "train.seconds": float(trainer.train_seconds),
        "train.skipped": float(trainer.skipped_steps),
        "train.seed": float(trainer.seed),
        "train.frames_seen": float(trainer.store.seen),
    }
    arrays["train.config_json"] = json_to_array(
        {"config": trainer.config.to_dict(), "body_model": trainer.body_reference}
    )
    arrays["train.betas"] = _np(trainer.betas).reshape(-1)
    for name, state in trainer.optimizer.table_state().items():
        for key in STATE_KEYS:
            arrays[f"train.adam.{name}.{key}"] = _np(state[key])
        meta[f"train.adam.{name}.step"] = float(state["step"])
    if trainer.optimizer.dense is not None:
        for group in trainer.optimizer.dense.param_groups:
            for i, p in enumerate(group["params"]):
                state = trainer.optimizer.dense.state.get(p)
                if not state:
                    continue
                for key in STATE_KEYS:
                    arrays[f"train.dense.{group['name']}.{i}.{key}"] = _np(state[key])
                meta[f"train.dense.{group['name']}.{i}.step"] = float(state["step"])
    if trainer.pose_deltas is not None:
        arrays["train.pose_deltas"] = _np(trainer.pose_deltas)
        slots = sorted(trainer.pose_slots.items(), key=lambda kv: kv[1])
        arrays["train.pose_frames"] = np.asarray([f for f, _ in slots], np.float32)
    for name, value in trainer.exposure.state_arrays().items():
        arrays[f"train.exposure.{name}"] = value
    d = trainer.densifier
    for name, value in d.state_arrays().items():
        arrays[f"train.densify.{name}"] = _np(value)
    if d.initial_part_counts is not None:
        arrays["train.densify.initial_parts"] = _np(d.initial_part_counts)
    meta["train.densify.steps_seen"] = float(d.steps_seen)
    for name, value in trainer.isometry.state_arrays().items():
        arrays[f"train.isometry.{name}"] = _np(value)
    for name, value in d.counts.items():
        meta[f"train.densify.count.{name}"] = float(value)
    for name, value in trainer.weights.ema.items():
        meta[f"train.ema.{name}"] = float(value)
    for name, value in trainer.notes.items():
        meta[f"train.notes.{name}"] = float(value)
    return arrays, meta


def save(trainer, path: str | Path) -> Path:
    arrays, meta = training_state(trainer)
    msg = to_snapshot(
        trainer.model,
        iteration=trainer.iteration,
        model_version=trainer.model_version,
        extra_arrays=arrays,
        extra_meta=meta,
    )
    return write_snapshot_file(path, msg)


def load(path: str | Path, *, body_model=None, device="cpu", backend="auto", flow_cache=None, config=None):
    """A Trainer continuing exactly where the checkpoint at ``path`` stopped."""
    from stg_node.avatar.trainer import Trainer

    msg = read_snapshot_file(path)
    arrays, meta = msg.arrays, msg.meta
    if "train.config_json" not in arrays:
        raise ValueError(f"{path} is a published snapshot, not a training checkpoint (no train.* state)")
    stored = array_to_json(arrays["train.config_json"])
    cfg = config or TrainConfig.from_dict(stored["config"])
    body = body_model if body_model is not None else stored.get("body_model")
    trainer = Trainer(
        cfg, body, device=device, backend=backend, seed=int(meta["train.seed"]), flow_cache=flow_cache
    )
    dev = trainer.device

    def t(name):
        return torch.as_tensor(np.array(arrays[name], np.float32), device=dev)

    model = model_from_snapshot(msg, device=dev)
    trainer.attach_model(model, t("train.betas")[None])
    if "train.pose_deltas" in arrays:
        frames = [int(f) for f in np.asarray(arrays["train.pose_frames"])]
        trainer.pose_slots = {f: i for i, f in enumerate(frames)}
        trainer.pose_deltas = torch.nn.Parameter(t("train.pose_deltas"))
    trainer._build_optimizer()
    trainer.exposure.load_state_arrays(
        {k[len("train.exposure.") :]: v for k, v in arrays.items() if k.startswith("train.exposure.")}
    )
    table_states = {}
    for name in model.table.trainable_names():
        key = f"train.adam.{name}.step"
        if key in meta:
            table_states[name] = {
                "step": torch.tensor(meta[key]),
                **{k: t(f"train.adam.{name}.{k}") for k in STATE_KEYS},
            }
    trainer.optimizer.load_table_state(table_states)
    if trainer.optimizer.dense is not None:
        for group in trainer.optimizer.dense.param_groups:
            for i, p in enumerate(group["params"]):
                key = f"train.dense.{group['name']}.{i}.step"
                if key in meta:
                    trainer.optimizer.dense.state[p] = {
                        "step": torch.tensor(meta[key]),
                        **{k: t(f"train.dense.{group['name']}.{i}.{k}") for k in STATE_KEYS},
                    }
    d = trainer.densifier
    d.reset(model)
    d.load_state_arrays(
        {n: t(f"train.densify.{n}") for n in d.STATE if f"train.densify.{n}" in arrays},
        int(meta.get("train.densify.steps_seen", 0)),
    )
    if "train.densify.initial_parts" in arrays:
        d.initial_part_counts = t("train.densify.initial_parts")
    d.counts = {
        k[len("train.densify.count.") :]: int(v)
        for k, v in meta.items()
        if k.startswith("train.densify.count.")
    }
    trainer.weights.ema = {
        k[len("train.ema.") :]: float(v) for k, v in meta.items() if k.startswith("train.ema.")
    }
    trainer.notes = {
        k[len("train.notes.") :]: float(v) for k, v in meta.items() if k.startswith("train.notes.")
    }
    trainer.isometry.load_state_arrays(
        {k[len("train.isometry.") :]: t(k) for k in arrays if k.startswith("train.isometry.")}, model.table
    )
    trainer.iteration = int(meta["train.iteration"])
    trainer.train_seconds = float(meta["train.seconds"])
    trainer.skipped_steps = int(meta["train.skipped"])
    trainer.model_version = int(msg.model_version)
    return trainer
