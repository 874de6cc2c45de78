"""SMPL pose files: reading and writing them in the formats real data uses, and driving any body with them.

Formats read by :func:`load_smpl_params` (all into a :class:`~stg_node.body.params.SmplSequence`):

- ZJU-MoCap / EasyMocap ``new_params/{i}.npy``: a pickled dict with ``poses (1, 72)``,
  ``Rh (1, 3)``, ``Th (1, 3)``, ``shapes (1, 10)`` (read by :func:`stg_node.safe_load.load_npy`,
  which refuses anything but arrays and plain containers); a directory of them is a sequence,
  ordered by frame number.
- ``.npz`` with ``poses (T, 72)`` or ``(T, 24, 3)``, ``Rh (T, 3)``, ``Th (T, 3)`` and ``shapes``
  or ``betas`` (the layout :func:`save_smpl_params` writes).
- AMASS-style ``.npz`` (``poses (T, 156)`` SMPL-H axis-angle, ``trans (T, 3)``, ``betas``): the
  22 body joints are kept, SMPL's two hand joints set to zero, ``Th = trans``, ``Rh = 0``.

:func:`drive_body` is the one code path that poses a body with SMPL parameters: the official
SMPL model and the open body go through it alike, because both are SMPL-format models.
Procedural motion for tests and demos comes from :func:`stg_node.data.synth.motions.make_motion`.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch

from stg_node.body.params import SmplParams, SmplSequence
from stg_node.body.smpl_io import SMPL_NUM_JOINTS
from stg_node.safe_load import load_npy, load_npz

NUM_POSE = SMPL_NUM_JOINTS * 3


def _field(data: dict, names: tuple[str, ...], source: str, width: int | None = None) -> np.ndarray:
    for name in names:
        if name in data:
            try:
                value = np.asarray(data[name], dtype=np.float32)
            except (TypeError, ValueError) as exc:
                raise ValueError(f"{source}: {name!r} is not numeric ({exc})") from None
            if value.ndim == 1:
                value = value[None]
            if value.ndim == 3 and width == NUM_POSE and value.shape[1:] == (SMPL_NUM_JOINTS, 3):
                value = value.reshape(len(value), NUM_POSE)
            if value.ndim != 2 or (width is not None and value.shape[1] != width):
                raise ValueError(f"{source}: {name!r} has shape {value.shape}, expected (T, {width or 'S'})")
            if not np.all(np.isfinite(value)):
                raise ValueError(f"{source}: {name!r} contains NaN or infinite values")
            return value
    raise ValueError(f"{source}: missing {' or '.join(repr(n) for n in names)} (keys: {sorted(data)})")


def _scalar(data: dict, name: str, source: str) -> float | None:
    """An optional positive number (a frame rate); None when absent."""
    if name not in data:
        return None
    try:
        value = float(np.asarray(data[name], dtype=np.float64).reshape(-1)[0])
    except (TypeError, ValueError, IndexError) as exc:
        raise ValueError(f"{source}: {name!r} is not a number ({exc})") from None
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"{source}: {name!r} must be a positive number, got {value}")
    return value


def _from_dict(data: dict, source: str) -> SmplSequence:
    if not isinstance(data, dict):
        raise ValueError(f"{source}: expected a dict of SMPL parameters, got {type(data).__name__}")
    if "trans" in data and "Th" not in data:  # AMASS-style
        poses = _field(data, ("poses",), source)
        if poses.ndim != 2 or poses.shape[1] < 66:
            raise ValueError(f"{source}: AMASS 'poses' has shape {poses.shape}, expected (T, >= 66)")
        body = np.concatenate([poses[:, :66], np.zeros((len(poses), 6), np.float32)], axis=1)
        trans = _field(data, ("trans",), source, 3)
        betas = _field({"betas": data.get("betas", np.zeros(10))}, ("betas",), source).reshape(-1)[:16]
        fps = _scalar(data, "mocap_framerate", source)
        return SmplSequence(body, np.zeros_like(trans), trans, betas, fps, source)
    poses = _field(data, ("poses", "pose"), source, NUM_POSE)
    rh = _field(data, ("Rh",), source, 3)
    th = _field(data, ("Th",), source, 3)
    betas = _field(data, ("shapes", "betas"), source)
    count = len(poses)
    if len(rh) != count or len(th) != count or len(betas) not in (1, count):
        raise ValueError(
            f"{source}: inconsistent frame counts poses {count}, Rh {len(rh)}, Th {len(th)}, "
            f"shapes {len(betas)}"
        )
    fps = _scalar(data, "fps", source)
    return SmplSequence(poses, rh, th, betas[0] if len(betas) == 1 and count > 1 else betas, fps, source)


def _frame_number(path: Path) -> int:
    match = re.search(r"(\d+)$", path.stem)
    return int(match.group(1)) if match else -1


def load_smpl_params(path: str | Path) -> SmplSequence:
    """Read one SMPL parameter file or a directory of per-frame ``.npy`` files (see module doc).

    Raises FileNotFoundError for a missing file, ``ValueError`` naming the file and the field for
    bad contents, and :class:`stg_node.safe_load.RefusedPickleError` for a pickle that would run code.
    """
    path = Path(path)
    if path.is_dir():
        files = sorted(path.glob("*.npy"), key=lambda p: (_frame_number(p), p.name))
        if not files:
            raise FileNotFoundError(f"{path}: no per-frame .npy SMPL parameter files")
        frames = [load_smpl_params(f).frame(0) for f in files]
        return SmplSequence.from_frames(frames, source=str(path))
    if not path.is_file():
        raise FileNotFoundError(f"SMPL parameter file not found: {path}")
    if path.suffix == ".npy":
        data = load_npy(path)
    elif path.suffix == ".npz":
        data = load_npz(path)
    else:
        raise ValueError(f"{path}: SMPL parameters must be .npy (ZJU-MoCap new_params) or .npz")
    return _from_dict(data, str(path))


def save_smpl_params(path: str | Path, params: SmplSequence | SmplParams) -> None:
    """Write a sequence as ``.npz`` (poses (T, 72), Rh, Th, shapes, fps), or one frame as a
    ZJU-MoCap ``new_params`` ``.npy`` dict (float32 arrays with a leading axis of 1)."""
    path = Path(path)
    if isinstance(params, SmplParams):
        params = SmplSequence.from_frames([params])
    count = len(params)
    poses = params.poses.reshape(count, NUM_POSE)
    betas = np.atleast_2d(params.betas)
    if path.suffix == ".npy":
        if count != 1:
            raise ValueError("a ZJU-style .npy file holds one frame; use .npz for a sequence")
        np.save(path, {"poses": poses, "Rh": params.Rh, "Th": params.Th, "shapes": betas[:1]})
        return
    extra = {"fps": np.float32(params.fps)} if params.fps else {}
    np.savez_compressed(path, poses=poses, Rh=params.Rh, Th=params.Th, shapes=betas, **extra)


def drive_body(model, params: SmplSequence | SmplParams, frames=None, pose_blendshapes: bool = True):
    """Pose ``model`` (any SMPL-format BodyModel) with SMPL parameters.

    Returns one BodyOutput batched over the frames (all of them, or ``frames``: an index, slice or
    list; a single :class:`SmplParams` is a batch of one). The official SMPL model and the open
    body take exactly this path.
    """
    if isinstance(params, SmplParams):
        params = SmplSequence.from_frames([params])
    if frames is not None:
        params = params[np.atleast_1d(np.arange(len(params))[frames])]
    like = model.v_template

    def tensor(array):
        return torch.as_tensor(np.asarray(array), dtype=like.dtype, device=like.device)

    return model(
        betas=tensor(params.betas),
        poses=tensor(params.poses),
        Rh=tensor(params.Rh),
        Th=tensor(params.Th),
        pose_blendshapes=pose_blendshapes,
    )
