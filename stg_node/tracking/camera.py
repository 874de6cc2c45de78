"""Camera intrinsics for tracking: a calibration file, or a pinhole from a field of view.

``--intrinsics FILE.json`` holds ``{"K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], "dist": [k1, k2, p1,
p2, k3, ...]}`` (``dist`` optional: OpenCV's distortion coefficients, 4, 5, 8, 12 or 14 values),
in pixels of the video as recorded. Without a file the camera is a distortion-free pinhole with
the principal point at the image centre and the horizontal field of view ``fov_deg``
(:data:`DEFAULT_FOV_DEG`: a typical webcam or phone main camera; the pose is little affected by
a wrong guess, the distance to the person scales with it).

Keypoints are undistorted (``cv2.undistortPoints``) before fitting, so the fitted parameters
belong to the pinhole camera ``K``; images are left as they are (undistort them with the same
``K``/``dist`` before training on them).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

DEFAULT_FOV_DEG = 65.0  # horizontal; webcams 60-78, phone main cameras 65-70
DIST_COUNTS = (4, 5, 8, 12, 14)


class IntrinsicsError(ValueError):
    """A calibration file or value is unusable; the message names the file and the problem."""


@dataclass(frozen=True)
class Intrinsics:
    K: np.ndarray  # (3, 3) float64
    dist: np.ndarray | None  # (n,) OpenCV distortion coefficients, or None
    width: int
    height: int
    source: str  # "file:PATH" or "fov:DEG"

    def scaled(self, width: int, height: int) -> Intrinsics:
        """The same camera for frames resized to ``width x height`` (pixel centres kept)."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0, 0] *= sx
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 1] *= sy
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return Intrinsics(K, self.dist, width, height, self.source)

    def undistort_points(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) distorted pixel positions -> pinhole pixel positions under ``K``."""
        xy = np.asarray(xy, dtype=np.float64)
        if self.dist is None or not np.any(self.dist) or xy.size == 0:
            return xy.copy()
        out = cv2.undistortPoints(xy.reshape(-1, 1, 2), self.K, self.dist, P=self.K)
        return out.reshape(-1, 2)

    def undistort_mask(self, mask: np.ndarray) -> np.ndarray:
        """An (H, W) mask of the distorted image resampled to the pinhole image under ``K`` (the
        frame the fit projects into); the mask itself when there is no distortion."""
        if self.dist is None or not np.any(self.dist):
            return mask
        return cv2.undistort(mask, self.K, self.dist, None, self.K)

    def to_json(self) -> dict:
        return {"K": self.K.tolist(), "dist": None if self.dist is None else self.dist.tolist()}


def from_fov(width: int, height: int, fov_deg: float = DEFAULT_FOV_DEG) -> Intrinsics:
    """A pinhole with horizontal field of view ``fov_deg`` and the principal point at the centre."""
    if not 1.0 <= fov_deg <= 170.0:
        raise IntrinsicsError(f"--fov must be between 1 and 170 degrees, got {fov_deg}")
    if width < 1 or height < 1:
        raise IntrinsicsError(f"image size must be positive, got {width}x{height}")
    focal = (width / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
    K = np.array([[focal, 0.0, (width - 1) / 2.0], [0.0, focal, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    return Intrinsics(K, None, width, height, f"fov:{fov_deg:g}")


def load_intrinsics(path: str | Path, width: int, height: int) -> Intrinsics:
    """Read ``{"K": 3x3, "dist": [...]}``; the principal point must lie inside the image."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise IntrinsicsError(f"{path}: intrinsics file does not exist") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise IntrinsicsError(f"{path}: cannot be read as JSON ({exc})") from exc
    if not isinstance(data, dict) or "K" not in data:
        raise IntrinsicsError(f'{path}: expected a JSON object with "K" (3x3) and optionally "dist"')
    try:
        K = np.asarray(data["K"], dtype=np.float64)
    except (TypeError, ValueError):
        raise IntrinsicsError(f'{path}: "K" is not a numeric 3x3 matrix') from None
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise IntrinsicsError(f'{path}: "K" must be a finite 3x3 matrix, got shape {K.shape}')
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
        raise IntrinsicsError(f'{path}: "K" must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0')
    if not (0 <= K[0, 2] < width and 0 <= K[1, 2] < height):
        raise IntrinsicsError(
            f"{path}: principal point ({K[0, 2]:.1f}, {K[1, 2]:.1f}) lies outside the {width}x{height} "
            "frames (is the file for another resolution?)"
        )
    dist = data.get("dist")
    if dist is not None:
        try:
            dist = np.asarray(dist, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise IntrinsicsError(f'{path}: "dist" is not a list of numbers') from None
        if dist.size not in DIST_COUNTS or not np.all(np.isfinite(dist)):
            raise IntrinsicsError(f'{path}: "dist" must hold {DIST_COUNTS} finite values, got {dist.size}')
    return Intrinsics(K, dist, width, height, f"file:{path}")


def smpl_to_world(smpl, R: np.ndarray, t: np.ndarray):
    """Camera-frame SMPL parameters (what the tracker gives) -> a world frame with world-to-camera ``R, t``.

    ``x_cam = R x_world + t`` and ``x_cam = R(Rh) p + Th`` give ``x_world = (R^T R(Rh)) p + R^T (Th - t)``:
    the pose and shape are unchanged, ``Rh`` and ``Th`` are re-expressed.
    """
    import dataclasses

    import torch

    from stg_node.body import lbs

    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape(3)
    rotation = R.T @ lbs.axis_angle_to_matrix(torch.as_tensor(smpl.Rh, dtype=torch.float64)).numpy()
    Rh = lbs.matrix_to_axis_angle(torch.as_tensor(rotation)).numpy()
    Th = R.T @ (np.asarray(smpl.Th, dtype=np.float64) - t)
    return dataclasses.replace(smpl, Rh=Rh, Th=Th)
