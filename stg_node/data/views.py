"""Turning a raw calibrated view into what the trainer sees: undistorted, resized, masked.

The order is the one the ZJU-MoCap literature uses (Neural Body, 3DGS-Avatar): undistort at
the native resolution keeping the same intrinsics (``cv2.undistort(img, K, D)``), then resize,
then paint the background black. Two details differ on purpose:

- ``K`` is rescaled with the pixel-centre convention of ``cv2.resize``
  (``c' = (c + 0.5) * s - 0.5``, ``f' = f * s``), so a 3D point lands on the same image content
  after resizing; the usual ``K[:2] *= s`` is off by ``(s - 1) / 2`` pixels (a quarter pixel at
  1024 -> 512).
- Masks are resized by area averaging and thresholded at one half instead of nearest-neighbour
  sampling, which in OpenCV picks the top-left source pixel and shifts the mask by the same
  quarter pixel.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from stg_node.data.errors import DatasetError
from stg_node.data.types import Camera


@dataclass(frozen=True)
class RawCamera:
    """A camera as stored by a dataset: native size, OpenCV distortion, world-to-camera pose."""

    name: str
    K: np.ndarray  # (3, 3) intrinsics in native pixels
    D: np.ndarray  # (N,) OpenCV distortion (k1, k2, p1, p2[, k3 ...]); zeros if none
    R: np.ndarray  # (3, 3) world -> camera rotation
    t: np.ndarray  # (3,) translation, metres
    width: int
    height: int

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.D != 0))


def output_size(size: int | tuple[int, int] | None, width: int, height: int) -> tuple[int, int]:
    """``(width, height)`` of delivered images: an int means square, None keeps the native size."""
    if size is None:
        return width, height
    if isinstance(size, int | np.integer):
        if size <= 0:
            raise ValueError(f"size must be positive, got {size}")
        return int(size), int(size)
    w, h = (int(v) for v in size)
    if w <= 0 or h <= 0:
        raise ValueError(f"size must be positive, got {size}")
    return w, h


def scale_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Intrinsics after ``cv2.resize`` by (sx, sy), with cv2's pixel-centre convention."""
    out = np.array(K, dtype=np.float64, copy=True)
    out[0, 0] *= sx
    out[0, 1] *= sx
    out[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    out[1, 1] *= sy
    out[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return out


@dataclass
class ViewPreparer:
    """Undistorts, resizes and masks the images of one camera; holds the delivered :class:`Camera`."""

    raw: RawCamera
    size: int | tuple[int, int] | None = 512
    camera: Camera = field(init=False)
    _maps: tuple[np.ndarray, np.ndarray] | None = field(init=False, default=None, repr=False)

    def __post_init__(self) -> None:
        w, h = output_size(self.size, self.raw.width, self.raw.height)
        K = scale_intrinsics(self.raw.K, w / self.raw.width, h / self.raw.height)
        self.camera = Camera(
            K=K,
            R=np.asarray(self.raw.R, np.float64),
            t=np.asarray(self.raw.t, np.float64),
            width=w,
            height=h,
            name=self.raw.name,
        )

    def _undistort_maps(self) -> tuple[np.ndarray, np.ndarray]:
        if self._maps is None:
            size = (self.raw.width, self.raw.height)
            self._maps = cv2.initUndistortRectifyMap(
                self.raw.K, self.raw.D, None, self.raw.K, size, cv2.CV_32FC1
            )
        return self._maps

    def __call__(
        self,
        image: np.ndarray,
        mask: np.ndarray,
        *,
        image_path: Path | str | None = None,
        mask_path: Path | str | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(image, mask)`` as delivered: RGB uint8 black outside the mask, mask uint8 0/255."""
        native = (self.raw.height, self.raw.width)
        if image.shape[:2] != native:
            raise DatasetError(
                image_path,
                f"image is {image.shape[1]}x{image.shape[0]}",
                f"{self.raw.width}x{self.raw.height} like the other images of camera {self.raw.name}",
            )
        if mask.shape[:2] != native:
            raise DatasetError(
                mask_path,
                f"mask is {mask.shape[1]}x{mask.shape[0]}",
                f"{self.raw.width}x{self.raw.height}, the size of its image",
            )
        if self.raw.has_distortion:
            map_x, map_y = self._undistort_maps()
            image = cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            mask = cv2.remap(mask, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            mask = np.where(mask >= 128, np.uint8(255), np.uint8(0))
        w, h = self.camera.width, self.camera.height
        if (w, h) != (self.raw.width, self.raw.height):
            shrinking = w < self.raw.width and h < self.raw.height
            image = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR)
            mask = cv2.resize(mask, (w, h), interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR)
            mask = np.where(mask >= 128, np.uint8(255), np.uint8(0))
        image = np.ascontiguousarray(image)
        image[mask == 0] = 0
        return image, np.ascontiguousarray(mask)


def project(points: np.ndarray, camera: Camera) -> np.ndarray:
    """Pixel coordinates ``(N, 2)`` of world points ``(N, 3)`` in a delivered (pinhole) camera."""
    cam = points @ camera.R.T + camera.t
    uv = cam @ camera.K.T
    return uv[:, :2] / uv[:, 2:3]
