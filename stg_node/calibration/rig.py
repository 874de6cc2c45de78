"""rig.json: the calibration of a rig of cameras (the format is a contract; docs/RIGS.md).

::

    {"cameras": {NAME: {"K": 3x3, "dist": [k1, k2, p1, p2, k3, ...], "R": 3x3, "t": [3],
                        "image_size": [w, h]}, ...},
     "calibration": {...}}            (optional: how it was made, reprojection error per camera)

OpenCV conventions: ``K`` in pixels of frames of ``image_size``; ``dist`` OpenCV's distortion
coefficients (4, 5, 8, 12 or 14 values, or empty); ``R``, ``t`` map world to camera
(``x_cam = R x_world + t``), metres. The order of ``cameras`` is the rig's camera order (inputs
to ``stg-track`` are given in it). ``stg-calibrate`` writes it; the tracker, ``stg-train`` and
the rig's ingest read it. Only numpy and json here: nodes read rig files without OpenCV or torch.
"""

from __future__ import annotations

import json
import os
import re
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

DIST_COUNTS = (0, 4, 5, 8, 12, 14)
NAME_PATTERN = re.compile(r"^[A-Za-z0-9_.-]+$")  # also a topic part and a folder name


class RigError(ValueError):
    """A rig file or a camera in it is unusable; the message names the file and the problem."""


@dataclass(frozen=True)
class RigCamera:
    """One calibrated camera of a rig."""

    name: str
    K: np.ndarray  # (3, 3) float64, pixels of image_size frames
    dist: np.ndarray  # (n,) OpenCV distortion coefficients; n = 0 for none
    R: np.ndarray  # (3, 3) world -> camera
    t: np.ndarray  # (3,) metres
    image_size: tuple[int, int]  # (width, height)

    @property
    def center(self) -> np.ndarray:
        """The camera's position in the world (metres)."""
        return -self.R.T @ self.t

    @property
    def width(self) -> int:
        return int(self.image_size[0])

    @property
    def height(self) -> int:
        return int(self.image_size[1])

    def to_json(self) -> dict:
        return {
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
            "R": self.R.tolist(),
            "t": self.t.tolist(),
            "image_size": [int(self.image_size[0]), int(self.image_size[1])],
        }

    def camera(self):
        """The :class:`stg_node.data.types.Camera` (pinhole part) of this camera."""
        from stg_node.data.types import Camera

        return Camera(K=self.K, R=self.R, t=self.t, width=self.width, height=self.height, name=self.name)


@dataclass(frozen=True)
class Rig:
    """The cameras of a rig, in order, and how they were calibrated (free-form, may be empty)."""

    cameras: tuple[RigCamera, ...]
    calibration: dict = field(default_factory=dict)

    def __post_init__(self):
        names = [c.name for c in self.cameras]
        if not names:
            raise RigError("a rig needs at least one camera")
        if len(set(names)) != len(names):
            raise RigError(f"camera names must be unique, got {names}")

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def __len__(self) -> int:
        return len(self.cameras)

    def __getitem__(self, name: str) -> RigCamera:
        for camera in self.cameras:
            if camera.name == name:
                return camera
        raise KeyError(f"no camera {name!r} in the rig; its cameras: {', '.join(self.names)}")

    def select(self, names: list[str] | tuple[str, ...]) -> Rig:
        """The rig restricted to ``names``, in that order (a RigError naming the unknown ones)."""
        unknown = [n for n in names if n not in self.names]
        if unknown:
            raise RigError(f"camera(s) {unknown} are not in the rig; its cameras: {', '.join(self.names)}")
        if len(set(names)) != len(names):
            raise RigError(f"a camera is named twice in {list(names)}")
        return Rig(tuple(self[n] for n in names), self.calibration)

    def to_json(self) -> dict:
        out: dict = {"cameras": {c.name: c.to_json() for c in self.cameras}}
        if self.calibration:
            out["calibration"] = self.calibration
        return out


def _matrix(value, shape, where: str, what: str) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise RigError(f"{where}: {what} is not numeric") from None
    if array.shape != shape or not np.all(np.isfinite(array)):
        raise RigError(
            f"{where}: {what} must be a finite {'x'.join(map(str, shape))} array, got shape {array.shape}"
        )
    return array


def _numbers(value, where: str, what: str) -> np.ndarray:
    """``value`` as a flat float array, or a RigError naming the field."""
    try:
        return np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise RigError(f"{where}: {what} is not a list of numbers") from None


def camera_from_json(name: str, entry, where: str = "rig") -> RigCamera:
    """A :class:`RigCamera` from one ``cameras`` entry, every field checked."""
    where = f"{where}: camera {name!r}"
    if not NAME_PATTERN.match(name):
        raise RigError(f"{where}: a camera name may hold letters, digits, '_', '.' and '-' only")
    if not isinstance(entry, dict):
        raise RigError(f"{where}: expected an object with K, dist, R, t, image_size")
    missing = [k for k in ("K", "R", "t", "image_size") if k not in entry]
    if missing:
        raise RigError(f"{where}: lacks {missing} (each camera has K, dist, R, t, image_size)")
    K = _matrix(entry["K"], (3, 3), where, "K")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
        raise RigError(f"{where}: K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
    dist = _numbers(entry.get("dist") or [], where, "dist")
    if dist.size not in DIST_COUNTS or not np.all(np.isfinite(dist)):
        raise RigError(f"{where}: dist must hold {DIST_COUNTS[1:]} finite values (or none), got {dist.size}")
    R = _matrix(entry["R"], (3, 3), where, "R")
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0.99:
        raise RigError(f"{where}: R is not a rotation (R R^T = I, det 1), det {np.linalg.det(R):.4f}")
    t = _matrix(entry["t"], (3,), where, "t")
    size = _numbers(entry["image_size"], where, "image_size")
    if size.size != 2 or not np.all(size > 0) or not np.all(np.equal(np.mod(size, 1), 0)):
        raise RigError(f"{where}: image_size must be [width, height] in pixels, got {entry['image_size']}")
    width, height = int(size[0]), int(size[1])
    if not (0 <= K[0, 2] < width and 0 <= K[1, 2] < height):
        raise RigError(
            f"{where}: principal point ({K[0, 2]:.1f}, {K[1, 2]:.1f}) lies outside the {width}x{height} image"
        )
    return RigCamera(name, K, dist, R, t, (width, height))


def read_rig(path: str | Path) -> Rig:
    """Read and check a rig.json (a :class:`RigError` naming the file and field on any problem)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise RigError(f"{path}: rig file does not exist") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RigError(f"{path}: cannot be read as JSON ({exc})") from exc
    cameras = data.get("cameras") if isinstance(data, dict) else None
    if not isinstance(cameras, dict) or not cameras:
        raise RigError(
            f'{path}: expected {{"cameras": {{NAME: {{"K", "dist", "R", "t", "image_size"}}, ...}}}}'
        )
    calibration = data.get("calibration", {})
    return Rig(
        tuple(camera_from_json(str(name), entry, str(path)) for name, entry in cameras.items()),
        calibration if isinstance(calibration, dict) else {},
    )


def write_rig(path: str | Path, rig: Rig) -> Path:
    """Write atomically (a temporary file renamed into place)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(rig.to_json(), indent=2) + "\n"
    with tempfile.NamedTemporaryFile(
        "w", dir=path.parent, prefix=path.name, suffix=".tmp", delete=False
    ) as fh:
        fh.write(text)
    os.replace(fh.name, path)
    return path
