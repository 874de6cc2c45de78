"""An avatar as a GaussianSnapshot (the bus message), and checkpoints as files of that message.

The trainer node publishes exactly what ``stg-train`` saves: a GaussianSnapshot (format
``stg-avatar/1``) whose arrays are

- ``g.<column>``: every column of the Gaussian table (gaussians.py lists them);
- ``mlp.<name>``: the colour MLP's weights (colour mode "mlp");
- ``shading.<name>``: the learned light (``shading.light.*``: an ambient term and distant lights,
  or SH coefficients) and the mean training orientation (``shading.reference``,
  ``shading.orientation_sum``), shading mode "sh"; with ``model.occlusion`` the body's occluder
  spheres and the term's strength (``shading.occlusion.*``: occlusion.py);
- ``motion.bases`` (B, K, 3, 4): the shared affine motion bases at their K knots (``model.motion_basis``
  > 0; motion_basis.py), ``motion.knot_ids`` (K,): each knot's grid index less the first one's,
  which ``meta["motion.first_knot"]`` holds (a bounded trainer drops knots no held frame needs;
  a snapshot without them holds knots ``0..K-1``);
- ``body.rest_joints`` (24, 3), ``body.parents`` (24,), ``body.big_pose_inverse`` (24, 4, 4),
  ``body.betas`` (S,), ``body.bounds`` (2, 3): the skeleton, so a renderer needs no body file;
- ``time.pose_keys`` (F, 207), ``time.times`` (F,): the novel-pose time-code index;

and whose ``meta`` holds the numeric model settings (``model.*``; strings as indices into
their choices) and the time axis. A checkpoint adds ``train.*`` arrays and meta (Adam moments,
densification statistics, pose corrections, the TrainConfig as JSON bytes, counters), which a
renderer ignores; :func:`strip_training_state` gives the published message.

A snapshot *file* holds the message's bus frames (``[topic, header, *buffers]``) behind a small
length-prefixed container, written atomically (temp file, fsync, rename), so a process killed
mid-write leaves the previous checkpoint intact. Reading decodes through the bus codec, which
checks every array before anything is trusted.
"""

from __future__ import annotations

import dataclasses
import json
import os
import struct
from pathlib import Path

import numpy as np
import torch

from stg_node.avatar.config import (
    COLOR_MODES,
    LIGHT_MODELS,
    NORMAL_SIGNS,
    PREDATING_DEFAULTS,
    SKIN_INIT,
    ModelConfig,
)
from stg_node.avatar.gaussians import GaussianTable
from stg_node.avatar.model import AvatarModel
from stg_node.avatar.motion_basis import MotionBases
from stg_node.avatar.rigid import Skeleton
from stg_node.avatar.spacetime import TimeAxis
from stg_node.avatar.timecode import PoseTimeIndex

FORMAT = "stg-avatar/1"
FILE_MAGIC = b"STGSNAP1"
_STRING_CHOICES = {
    "color": COLOR_MODES,
    "skin_init": SKIN_INIT,
    "light_model": LIGHT_MODELS,
    "normal_sign": NORMAL_SIGNS,
}


class SnapshotError(ValueError):
    """A snapshot message or file that cannot be turned into an avatar (says which and why)."""


# --- model <-> message ----------------------------------------------------------------------------
def _np(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to("cpu", torch.float32).numpy())


def model_config_meta(config: ModelConfig) -> dict[str, float]:
    meta = {}
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if f.name in _STRING_CHOICES:
            value = _STRING_CHOICES[f.name].index(value)
        meta[f"model.{f.name}"] = float(value)
    return meta


def model_config_from_meta(meta: dict) -> ModelConfig:
    kwargs = {}
    predating = PREDATING_DEFAULTS["model"]
    for f in dataclasses.fields(ModelConfig):
        key = f"model.{f.name}"
        if key not in meta:
            if f.name in predating:  # a snapshot from before the setting: what it was made with
                kwargs[f.name] = predating[f.name]
            continue
        value = meta[key]
        if f.name in _STRING_CHOICES:
            value = _STRING_CHOICES[f.name][int(value)]
        elif f.type in ("bool", bool):
            value = bool(value)
        elif f.type in ("int", int):
            value = int(value)
        kwargs[f.name] = value
    return ModelConfig(**kwargs)


def model_arrays(model: AvatarModel) -> dict[str, np.ndarray]:
    arrays = {f"g.{name}": _np(model.table[name]) for name in model.table.names()}
    if model.color_mlp is not None:
        for name, value in model.color_mlp.state_dict().items():
            if name != "bounds":
                arrays[f"mlp.{name}"] = _np(value)
    if model.shading is not None:
        for name, value in model.shading.state_dict().items():
            arrays[f"shading.{name}"] = _np(value)
    sk = model.skeleton
    arrays["body.rest_joints"] = _np(sk.rest_joints)
    arrays["body.parents"] = _np(sk.parents.float())
    arrays["body.big_pose_inverse"] = _np(sk.big_pose_inverse)
    arrays["body.bounds"] = _np(model.bounds)
    if model.motion_bases is not None:
        arrays["motion.bases"] = _np(model.motion_bases.values)
        # the knots' grid indices less the first one's (meta motion.first_knot): exact in float32
        ids = model.motion_bases.knot_ids
        arrays["motion.knot_ids"] = (ids - ids[0]).astype(np.float32)
    arrays["time.pose_keys"] = np.ascontiguousarray(model.pose_index.keys, np.float32)
    arrays["time.times"] = np.ascontiguousarray(model.pose_index.times, np.float32)
    return arrays


def model_nbytes(model: AvatarModel) -> int:
    """Bytes of what a renderer needs (the published snapshot's arrays)."""
    return sum(a.nbytes for a in model_arrays(model).values())


def to_snapshot(
    model: AvatarModel, *, iteration: int = 0, model_version: int = 0, extra_arrays=None, extra_meta=None
):
    """The GaussianSnapshot message of ``model`` (plus training state when given)."""
    from stg_node.bus.messages import GaussianSnapshot

    arrays = model_arrays(model)
    meta = model_config_meta(model.config)
    meta["time.origin_s"] = float(model.time_axis.origin_s)
    meta["time.unit_s"] = float(model.time_axis.unit_s)
    if model.motion_bases is not None:
        meta["motion.first_knot"] = float(model.motion_bases.first_knot)
    if extra_arrays:
        arrays.update(extra_arrays)
    if extra_meta:
        meta.update(extra_meta)
    return GaussianSnapshot(
        format=FORMAT,
        model_version=int(model_version),
        iteration=int(iteration),
        num_gaussians=int(model.table.num),
        meta=meta,
        arrays=arrays,
    )


def strip_training_state(msg):
    """The message without ``train.*`` arrays and meta: what a renderer needs."""
    return dataclasses.replace(
        msg,
        arrays={k: v for k, v in msg.arrays.items() if not k.startswith("train.")},
        meta={k: v for k, v in msg.meta.items() if not k.startswith("train.")},
    )


def model_from_snapshot(msg, device="cpu") -> AvatarModel:
    """Rebuild the avatar from a GaussianSnapshot; a SnapshotError says what is missing or wrong."""
    if msg.format != FORMAT:
        raise SnapshotError(f"snapshot format is {msg.format!r}; this renderer reads {FORMAT!r}")
    arrays, meta = msg.arrays, msg.meta
    try:
        config = model_config_from_meta(meta)
        config.validate()
    except (KeyError, IndexError, TypeError, ValueError) as exc:
        raise SnapshotError(f"snapshot meta does not describe a model: {exc}") from exc

    def get(name: str) -> torch.Tensor:
        if name not in arrays:
            raise SnapshotError(f"snapshot has no array {name!r}")
        return torch.as_tensor(np.array(arrays[name], np.float32), device=device)

    columns = {k[2:]: get(k) for k in arrays if k.startswith("g.")}
    for needed in ("means", "log_scales", "quats", "opacity_logits", "skin_weights"):
        if needed not in columns:
            raise SnapshotError(f"snapshot has no Gaussian column {needed!r}")
    n = columns["means"].shape[0]
    bad = {k: tuple(v.shape) for k, v in columns.items() if v.shape[0] != n}
    if bad or n != msg.num_gaussians:
        raise SnapshotError(f"Gaussian columns disagree on the row count {n} / {msg.num_gaussians}: {bad}")
    try:
        table = GaussianTable(columns)
        skeleton = Skeleton(get("body.rest_joints"), get("body.parents").long(), get("body.big_pose_inverse"))
    except ValueError as exc:
        raise SnapshotError(str(exc)) from exc
    axis = TimeAxis(float(meta.get("time.origin_s", 0.0)), float(meta.get("time.unit_s", config.time_unit_s)))
    index = PoseTimeIndex()
    index.set(
        np.array(arrays.get("time.pose_keys", np.zeros((0, 207), np.float32))),
        np.array(arrays.get("time.times", np.zeros((0,), np.float32))),
    )
    model = AvatarModel(config, table, skeleton, get("body.bounds"), axis, index).to(device)
    if model.motion_bases is not None:
        try:
            values = get("motion.bases")
            ids = _knot_ids(msg, values.shape[1])
            knot_units = model.motion_bases.knot_units
            model.motion_bases = MotionBases(config.n_b, knot_units, values=values, knot_ids=ids)
        except ValueError as exc:
            raise SnapshotError(f"motion bases do not fit the model settings: {exc}") from exc
        model.motion_bases.to(device)
    if model.color_mlp is not None:
        state = {k[4:]: get(k) for k in arrays if k.startswith("mlp.")}
        state["bounds"] = model.bounds
        try:
            model.color_mlp.load_state_dict(state)
        except RuntimeError as exc:
            raise SnapshotError(f"colour MLP weights do not fit the model settings: {exc}") from exc
    if model.shading is not None:
        state = {k[len("shading.") :]: get(k) for k in arrays if k.startswith("shading.")}
        try:
            model.shading.load_state_dict(state)
        except RuntimeError as exc:
            raise SnapshotError(f"snapshot's light does not fit its shading settings: {exc}") from exc
    return model


def _knot_ids(msg, knots: int) -> np.ndarray:
    """The grid indices of the snapshot's knots; a snapshot from before the bounded trainer kept
    windowed knots has neither entry and holds knots ``0..K-1``."""
    first = msg.meta.get("motion.first_knot", 0.0)
    offsets = msg.arrays.get("motion.knot_ids")
    offsets = np.arange(knots, dtype=np.float64) if offsets is None else np.asarray(offsets, np.float64)
    if not float(first) >= 0 or float(first) != round(float(first)) or offsets.shape != (knots,):
        raise SnapshotError(
            f"motion.first_knot {first} / motion.knot_ids {offsets.shape} do not fit {knots} knots"
        )
    return np.round(offsets).astype(np.int64) + int(first)


# --- files ---------------------------------------------------------------------------------------
def write_snapshot_file(
    path: str | Path, msg, *, src: str = "stg-train", stamp_ns: int | None = None
) -> Path:
    """Write ``msg`` atomically as a snapshot file (see module docstring for the container)."""
    import time

    from stg_node.bus.codec import encode

    path = Path(path)
    frames = encode(
        msg,
        topic="avatar/snapshot",
        seq=int(msg.model_version),
        src=src,
        stamp_ns=int(time.time_ns() if stamp_ns is None else stamp_ns),
    )
    parts = [bytes(f) if not isinstance(f, (bytes, bytearray)) else f for f in frames]
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        fh.write(FILE_MAGIC)
        fh.write(struct.pack("<I", len(parts)))
        for part in parts:
            fh.write(struct.pack("<Q", len(part)))
        for part in parts:
            fh.write(memoryview(part).cast("B"))
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    return path


def read_snapshot_frames(path: str | Path) -> list[bytes]:
    path = Path(path)
    if not path.is_file():
        raise SnapshotError(f"{path}: no such snapshot file")
    data = path.read_bytes()
    if not data.startswith(FILE_MAGIC) or len(data) < len(FILE_MAGIC) + 4:
        raise SnapshotError(f"{path}: not a stg_node snapshot file (bad magic)")
    pos = len(FILE_MAGIC)
    (count,) = struct.unpack_from("<I", data, pos)
    pos += 4
    if count < 2 or count > 1024 or pos + 8 * count > len(data):
        raise SnapshotError(f"{path}: corrupt header ({count} frames)")
    sizes = struct.unpack_from(f"<{count}Q", data, pos)
    pos += 8 * count
    if pos + sum(sizes) != len(data):
        raise SnapshotError(
            f"{path}: truncated or padded ({len(data)} bytes, header says {pos + sum(sizes)})"
        )
    frames = []
    for size in sizes:
        frames.append(data[pos : pos + size])
        pos += size
    return frames


def read_snapshot_file(path: str | Path):
    """The GaussianSnapshot in ``path`` (checked by the bus decoder)."""
    from stg_node.bus.codec import decode
    from stg_node.bus.spec import MessageError

    frames = read_snapshot_frames(path)
    try:
        return decode(frames)
    except MessageError as exc:
        raise SnapshotError(f"{path}: {exc}") from exc


def json_to_array(obj) -> np.ndarray:
    return np.frombuffer(json.dumps(obj).encode(), np.uint8).astype(np.float32)


def array_to_json(arr: np.ndarray):
    return json.loads(np.asarray(arr).astype(np.uint8).tobytes().decode())
