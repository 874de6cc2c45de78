"""POSES.npz: what ``stg-track`` writes (the format is a contract; docs/TRACKING.md).

Required arrays, one row per input frame, in the camera's frame (OpenCV axes, metres), ZJU-MoCap's
convention ``x_camera = R(Rh) @ SMPL(poses, shapes) + Th``:

    poses       (N, 72) float32  axis-angle per joint in SMPL order; poses[:, :3] (SMPL's root) is 0
    Rh          (N, 3)  float32  global rotation (axis-angle, about the model origin)
    Th          (N, 3)  float32  translation
    shapes      (N, S)  float32  shape coefficients of the body model used (S = its count, 10 here)
    confidence  (N,)    float32  in [0, 1]; 0 where no person was found (the row then holds the last
                                 good pose); the trainer skips rows below its threshold

Extra arrays (readers may ignore them): ``frames`` (N,) int frame index in the input, ``times``
(N,) float seconds, ``K`` (3, 3) the pinhole camera the parameters belong to, ``dist`` (n,) the
input's distortion coefficients (empty when none), ``image_size`` (2,) width and height, ``fps``,
``body`` the body model's name, ``reprojection_px`` (N,) the fit's keypoint residual (NaN when
no fit), ``flags`` (N,) str why a frame's confidence is low (comma-separated: ``no_person``,
``cut_by_border``, ``motion_blur``, ``multiple_people``, ...; empty when nothing is wrong),
``camera`` a JSON object saying where ``K`` came from (a file, a given field of view, or the
focal length estimated from the footage with its interval and whether it is sure). From a rig
(``stg-track CAM1 CAM2 ... --calibration rig.json``): the parameters are in the rig's world frame,
``cameras`` (V,) names its cameras in input order and ``camera_frames`` (N, V) the frame of each
input every row used; ``K``, ``dist`` and ``image_size`` are then the first camera's (rig.json
holds them all). The required keys are also what ``stg_node.body.load_smpl_params`` and the
folder dataset's ``poses.npz`` read, so the file drops into either.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REQUIRED = ("poses", "Rh", "Th", "shapes", "confidence")


class PosesFileError(ValueError):
    """A POSES.npz file is missing arrays or has inconsistent shapes; the message names the file."""


@dataclass
class TrackedPoses:
    poses: np.ndarray  # (N, 72)
    Rh: np.ndarray  # (N, 3)
    Th: np.ndarray  # (N, 3)
    shapes: np.ndarray  # (N, S)
    confidence: np.ndarray  # (N,)
    frames: np.ndarray  # (N,) int64
    times: np.ndarray  # (N,) float64
    K: np.ndarray  # (3, 3)
    dist: np.ndarray  # (n,), empty when none
    image_size: tuple[int, int]  # width, height
    fps: float
    body: str = ""
    reprojection_px: np.ndarray | None = None  # (N,)
    cameras: tuple[str, ...] = ()  # a rig's camera names (world-frame parameters); () for one camera
    camera_frames: np.ndarray | None = None  # (N, V) int: a rig's input frame per row and camera
    flags: np.ndarray | None = None  # (N,) str, comma-separated reasons for a low confidence
    camera: str = ""  # JSON: where K came from (stg_node.tracking.focal)

    def __len__(self) -> int:
        return int(self.poses.shape[0])

    def validate(self, where: str = "poses") -> None:
        n = len(self)
        expected = {
            "poses": (n, 72),
            "Rh": (n, 3),
            "Th": (n, 3),
            "confidence": (n,),
            "frames": (n,),
            "times": (n,),
        }
        for name, shape in expected.items():
            if np.shape(getattr(self, name)) != shape:
                raise PosesFileError(
                    f"{where}: {name} has shape {np.shape(getattr(self, name))}, expected {shape}"
                )
        if self.shapes.ndim != 2 or self.shapes.shape[0] != n or self.shapes.shape[1] < 1:
            raise PosesFileError(f"{where}: shapes has shape {self.shapes.shape}, expected ({n}, S)")
        if np.shape(self.K) != (3, 3):
            raise PosesFileError(f"{where}: K has shape {np.shape(self.K)}, expected (3, 3)")
        for name in ("poses", "Rh", "Th", "shapes", "confidence"):
            if not np.all(np.isfinite(getattr(self, name))):
                raise PosesFileError(f"{where}: {name} contains NaN or infinite values")
        if np.any((self.confidence < 0) | (self.confidence > 1)):
            raise PosesFileError(f"{where}: confidence must lie in [0, 1]")
        if self.flags is not None and np.shape(self.flags) != (n,):
            raise PosesFileError(f"{where}: flags has shape {np.shape(self.flags)}, expected ({n},)")


def write_poses(path: str | Path, tracked: TrackedPoses) -> Path:
    """Write atomically (a temporary file renamed into place), so a crash never leaves half a file."""
    path = Path(path)
    tracked.validate(str(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {
        "poses": tracked.poses.astype(np.float32),
        "Rh": tracked.Rh.astype(np.float32),
        "Th": tracked.Th.astype(np.float32),
        "shapes": tracked.shapes.astype(np.float32),
        "confidence": tracked.confidence.astype(np.float32),
        "frames": tracked.frames.astype(np.int64),
        "times": tracked.times.astype(np.float64),
        "K": np.asarray(tracked.K, dtype=np.float64),
        "dist": np.asarray(tracked.dist, dtype=np.float64).reshape(-1),
        "image_size": np.asarray(tracked.image_size, dtype=np.int64),
        "fps": np.float64(tracked.fps),
        "body": np.array(tracked.body),
    }
    if tracked.reprojection_px is not None:
        arrays["reprojection_px"] = np.asarray(tracked.reprojection_px, dtype=np.float32)
    if tracked.cameras:
        arrays["cameras"] = np.asarray(tracked.cameras, dtype=str)
    if tracked.camera_frames is not None:
        arrays["camera_frames"] = np.asarray(tracked.camera_frames, dtype=np.int64)
    if tracked.flags is not None:
        arrays["flags"] = np.asarray(tracked.flags, dtype=str)
    if tracked.camera:
        arrays["camera"] = np.array(tracked.camera)
    with tempfile.NamedTemporaryFile(dir=path.parent, prefix=path.name, suffix=".tmp", delete=False) as fh:
        np.savez_compressed(fh, **arrays)
    os.replace(fh.name, path)
    return path


def read_poses(path: str | Path) -> TrackedPoses:
    path = Path(path)
    if not path.is_file():
        raise PosesFileError(f"{path}: no such file")
    try:
        with np.load(path, allow_pickle=False) as npz:
            data = {k: np.asarray(npz[k]) for k in npz.files}
    except Exception as exc:  # zipfile, numpy and OS errors alike
        raise PosesFileError(f"{path}: cannot be read as .npz ({type(exc).__name__}: {exc})") from exc
    missing = [k for k in REQUIRED if k not in data]
    if missing:
        raise PosesFileError(f"{path}: lacks {missing} (a POSES.npz holds {', '.join(REQUIRED)})")
    n = len(data["poses"])
    size = data.get("image_size", np.zeros(2, np.int64))
    tracked = TrackedPoses(
        poses=data["poses"].reshape(n, -1),
        Rh=data["Rh"],
        Th=data["Th"],
        shapes=data["shapes"].reshape(n, -1) if data["shapes"].ndim == 2 else np.tile(data["shapes"], (n, 1)),
        confidence=data["confidence"],
        frames=data.get("frames", np.arange(n)),
        times=data.get("times", np.arange(n, dtype=np.float64)),
        K=data.get("K", np.eye(3)),
        dist=data.get("dist", np.zeros(0)),
        image_size=(int(size[0]), int(size[1])),
        fps=float(data.get("fps", 0.0)),
        body=str(data.get("body", "")),
        reprojection_px=data.get("reprojection_px"),
        cameras=tuple(str(c) for c in data["cameras"]) if "cameras" in data else (),
        camera_frames=data.get("camera_frames"),
        flags=data.get("flags"),
        camera=str(data.get("camera", "")),
    )
    tracked.validate(str(path))
    return tracked
