"""SMPL pose sequences: reading them from the formats real data uses, and driving any body with them.

Formats read by :func:`load_smpl_params`:

- ZJU-MoCap / EasyMocap ``new_params/{i}.npy``: a pickled dict with ``poses (1, 72)``,
  ``Rh (1, 3)``, ``Th (1, 3)``, ``shapes (1, 10)`` (read by :func:`stg_node.safe_load.load_npy`); a
  directory of them is a sequence, ordered by frame number.
- ``.npz`` with ``poses (T, 72)``, ``Rh (T, 3)``, ``Th (T, 3)`` and ``shapes`` or ``betas``
  (the layout :func:`save_smpl_params` writes).
- AMASS-style ``.npz`` (``poses (T, 156)`` SMPL-H axis-angle, ``trans (T, 3)``, ``betas``): the
  22 body joints are kept, SMPL's two hand joints set to zero, ``Th = trans``, ``Rh = 0``.

:func:`drive_body` is the one code path that poses a body with a sequence: the official SMPL
model and the open body go through it alike, because both are SMPL-format models.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from stg_node.safe_load import load_npy, load_npz

NUM_POSE = 72


@dataclass
class SmplMotion:
    """A sequence of SMPL parameters in ZJU-MoCap's convention (``world = R(Rh) smpl + Th``)."""

    poses: np.ndarray  # (T, 72) float32 axis-angle
    Rh: np.ndarray  # (T, 3)
    Th: np.ndarray  # (T, 3)
    betas: np.ndarray  # (T, S) or (S,) shape coefficients
    fps: float | None = None
    source: str = ""

    def __len__(self) -> int:
        return int(self.poses.shape[0])

    def __getitem__(self, index) -> SmplMotion:
        sel = np.arange(len(self))[index]
        sel = np.atleast_1d(sel)
        betas = self.betas if self.betas.ndim == 1 else self.betas[sel]
        return SmplMotion(self.poses[sel], self.Rh[sel], self.Th[sel], betas, self.fps, self.source)


def _field(data: dict, names: tuple[str, ...], source: str, width: int | None = None) -> np.ndarray:
    for name in names:
        if name in data:
            value = np.asarray(data[name], dtype=np.float32)
            if value.ndim == 1:
                value = value[None]
            if value.ndim != 2 or (width is not None and value.shape[1] != width):
                raise ValueError(f"{source}: {name!r} has shape {value.shape}, expected (T, {width or 'S'})")
            if not np.all(np.isfinite(value)):
                raise ValueError(f"{source}: {name!r} contains NaN or infinite values")
            return value
    raise ValueError(f"{source}: missing {' or '.join(repr(n) for n in names)} (keys: {sorted(data)})")


def _from_dict(data: dict, source: str) -> SmplMotion:
    if not isinstance(data, dict):
        raise ValueError(f"{source}: expected a dict of SMPL parameters, got {type(data).__name__}")
    if "trans" in data and "Th" not in data:  # AMASS-style
        poses = np.asarray(data["poses"], dtype=np.float32)
        if poses.ndim != 2 or poses.shape[1] < 66:
            raise ValueError(f"{source}: AMASS 'poses' has shape {poses.shape}, expected (T, >= 66)")
        body = np.concatenate([poses[:, :66], np.zeros((len(poses), 6), np.float32)], axis=1)
        trans = _field(data, ("trans",), source, 3)
        betas = np.asarray(data.get("betas", np.zeros(10)), dtype=np.float32).reshape(-1)[:16]
        fps = float(data["mocap_framerate"]) if "mocap_framerate" in data else None
        return SmplMotion(body, np.zeros_like(trans), trans, betas, fps, source)
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
    fps = float(np.asarray(data["fps"])) if "fps" in data else None
    return SmplMotion(poses, rh, th, betas[0] if len(betas) == 1 and count > 1 else betas, fps, source)


def _frame_number(path: Path) -> int:
    match = re.search(r"(\d+)$", path.stem)
    return int(match.group(1)) if match else -1


def load_smpl_params(path: str | Path) -> SmplMotion:
    """Read one SMPL parameter file or a directory of per-frame ``.npy`` files (see module doc)."""
    path = Path(path)
    if path.is_dir():
        files = sorted(path.glob("*.npy"), key=lambda p: (_frame_number(p), p.name))
        if not files:
            raise FileNotFoundError(f"{path}: no per-frame .npy SMPL parameter files")
        frames = [load_smpl_params(f) for f in files]
        betas = np.stack([np.atleast_2d(f.betas)[0] for f in frames])
        return SmplMotion(
            np.concatenate([f.poses for f in frames]),
            np.concatenate([f.Rh for f in frames]),
            np.concatenate([f.Th for f in frames]),
            betas,
            None,
            str(path),
        )
    if not path.is_file():
        raise FileNotFoundError(f"SMPL parameter file not found: {path}")
    if path.suffix == ".npy":
        data = load_npy(path)
    elif path.suffix == ".npz":
        data = load_npz(path)
    else:
        raise ValueError(f"{path}: SMPL parameters must be .npy (ZJU-MoCap new_params) or .npz")
    return _from_dict(data, str(path))


def save_smpl_params(path: str | Path, motion: SmplMotion) -> None:
    """Write a sequence as ``.npz`` (poses, Rh, Th, shapes, fps), or one frame as a ZJU-style ``.npy``
    dict."""
    path = Path(path)
    betas = np.atleast_2d(motion.betas).astype(np.float32)
    if path.suffix == ".npy":
        if len(motion) != 1:
            raise ValueError("a ZJU-style .npy file holds one frame; use .npz for a sequence")
        np.save(path, {"poses": motion.poses, "Rh": motion.Rh, "Th": motion.Th, "shapes": betas[:1]})
        return
    extra = {"fps": np.float32(motion.fps)} if motion.fps else {}
    np.savez_compressed(path, poses=motion.poses, Rh=motion.Rh, Th=motion.Th, shapes=betas, **extra)


def drive_body(model, motion: SmplMotion, frames=None, pose_blendshapes: bool = True):
    """Pose ``model`` (any SMPL-format BodyModel) with frames of ``motion``.

    Returns one BodyOutput batched over the frames (all of them, or ``frames``: an index, slice or
    list). The official SMPL model and the open body take exactly this path.
    """
    if frames is not None:
        motion = motion[frames]
    like = model.v_template

    def tensor(array):
        return torch.as_tensor(np.asarray(array), dtype=like.dtype, device=like.device)

    return model(
        betas=tensor(motion.betas),
        poses=tensor(motion.poses),
        Rh=tensor(motion.Rh),
        Th=tensor(motion.Th),
        pose_blendshapes=pose_blendshapes,
    )


def procedural_walk(num_frames: int = 120, fps: float = 30.0, seed: int = 0, betas=None) -> SmplMotion:
    """A plausible SMPL walking sequence made from sinusoids (no captured data involved).

    One stride per second along a slow circle, arms swinging against the legs, a little trunk
    twist and head turn, and from half-way on the left arm waves. ``seed`` jitters amplitudes
    and phases, so different seeds give different walkers. Y-up world, ZJU convention.
    """
    rng = np.random.default_rng(seed)
    t = np.arange(num_frames) / fps
    jitter = lambda scale: 1.0 + scale * rng.uniform(-1, 1)  # noqa: E731
    stride = 2 * np.pi * 1.0 * jitter(0.1) * t + rng.uniform(0, 2 * np.pi)
    swing = np.sin(stride)
    poses = np.zeros((num_frames, 24, 3))
    hip = 0.45 * jitter(0.15)
    poses[:, 1, 0] = -hip * swing  # left hip: forward (negative x rotation) when swing > 0
    poses[:, 2, 0] = hip * swing
    knee = 0.7 * jitter(0.15)
    poses[:, 4, 0] = knee * np.clip(np.sin(stride + np.pi / 3), 0, None) + 0.05
    poses[:, 5, 0] = knee * np.clip(np.sin(stride + np.pi / 3 + np.pi), 0, None) + 0.05
    poses[:, 7, 0] = -0.15 * np.sin(stride + np.pi / 2)
    poses[:, 8, 0] = 0.15 * np.sin(stride + np.pi / 2)
    poses[:, 16, 2] = -1.2  # arms down along the body
    poses[:, 17, 2] = 1.2
    arm = 0.35 * jitter(0.2)
    poses[:, 16, 1] = arm * swing  # left arm forward when the right leg is
    poses[:, 17, 1] = arm * swing
    poses[:, 18, 1] = -0.35 - 0.15 * (1 + swing)
    poses[:, 19, 1] = 0.35 + 0.15 * (1 - swing)
    poses[:, 3, 1] = 0.08 * swing  # trunk counter-twist
    poses[:, 9, 1] = 0.06 * swing
    poses[:, 15, 1] = 0.3 * np.sin(2 * np.pi * 0.2 * t)  # looking around
    wave = t > t[-1] / 2 if num_frames > 1 else np.zeros(num_frames, bool)
    poses[wave, 16, 2] = 1.1  # left arm up ...
    poses[wave, 16, 1] = 0.0
    poses[wave, 18, 2] = 0.9 + 0.5 * np.sin(2 * np.pi * 1.5 * t[wave])  # ... waving from the elbow
    poses[wave, 18, 1] = 0.0
    # Walk on a circle of radius 2 m at about 0.8 m/s, facing along the path.
    radius = 2.0
    angle = 0.4 * t * jitter(0.1)
    heading = angle + np.pi / 2
    Rh = np.stack([np.zeros_like(t), heading, np.zeros_like(t)], axis=1)
    Th = np.stack([radius * np.sin(angle), 0.02 * np.cos(2 * stride), radius * np.cos(angle)], axis=1)
    Th[:, 1] += 1.2  # puts the feet of SMPL-sized bodies (soles at y = -1.2 in the model) on y = 0
    shape = np.zeros(10) if betas is None else np.asarray(betas, dtype=np.float64)
    return SmplMotion(
        poses.reshape(num_frames, 72).astype(np.float32),
        Rh.astype(np.float32),
        Th.astype(np.float32),
        shape.astype(np.float32),
        fps,
        f"procedural_walk(seed={seed})",
    )
