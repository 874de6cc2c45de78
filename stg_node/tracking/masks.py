"""Person masks per frame: four ways to tell the person from the background (docs/TRACKING.md).

- :class:`SegmentationMasker` (default with BlazePose): the landmark network's own person
  segmentation, inside the tracked region. Works with a moving camera and a busy background;
  soft at the edges, can miss loose clothing or held objects.
- :class:`PlateMasker`: difference to a captured empty plate (the scene without the person).
  Sharp and complete on a static camera with steady light; fails when the camera moves or the
  light changes, and marks shadows and anything else that moved.
- :class:`BackgroundModelMasker`: OpenCV's learned background (MOG2 or KNN). Needs no plate
  and adapts to slow light changes; a person who stands still long enough fades into the
  background, and the first second of frames only trains the model.
- :class:`DepthMasker`: an OAK's stereo depth aligned to the colour image, kept within a slab
  around the tracked person's distance. Immune to colours and light; ragged edges and holes
  where stereo finds no texture.

Every masker returns an (H, W) uint8 0/255 mask and is followed by :func:`clean_mask`: small
specks removed, holes closed, and only connected parts that touch the person's keypoints kept
(so a second person or a moving chair does not join the mask).
"""

from __future__ import annotations

from typing import Protocol

import cv2
import numpy as np

from stg_node.tracking.types import Keypoints

MASK_METHODS = ("segmentation", "plate", "mog2", "knn", "depth", "none")
SEGMENTATION_THRESHOLD = 0.5


class Masker(Protocol):
    def __call__(
        self, frame_rgb: np.ndarray, keypoints: Keypoints | None, depth_m: float | None
    ) -> np.ndarray: ...

    def reset(self) -> None: ...


def _check_frame(frame: np.ndarray) -> tuple[int, int]:
    if frame.ndim != 3 or frame.shape[2] != 3 or frame.dtype != np.uint8:
        raise ValueError(f"expected an (H, W, 3) uint8 RGB frame, got {frame.dtype} {frame.shape}")
    return frame.shape[0], frame.shape[1]


class SegmentationMasker:
    """Thresholds the pose network's person probability (Keypoints.segmentation)."""

    def __init__(self, threshold: float = SEGMENTATION_THRESHOLD):
        self.threshold = threshold

    def reset(self) -> None:
        pass

    def __call__(self, frame_rgb, keypoints, depth_m=None) -> np.ndarray:
        height, width = _check_frame(frame_rgb)
        if keypoints is None or keypoints.segmentation is None:
            return np.zeros((height, width), np.uint8)
        probability = np.asarray(keypoints.segmentation)
        if probability.shape != (height, width):
            probability = cv2.resize(probability, (width, height), interpolation=cv2.INTER_LINEAR)
        return np.where(probability >= self.threshold, np.uint8(255), np.uint8(0))


class PlateMasker:
    """Foreground = pixels that differ from an empty plate by more than ``threshold`` (0-255 scale)."""

    def __init__(self, plate_rgb: np.ndarray, threshold: float = 15.0, blur: int = 3):
        self.plate = np.asarray(plate_rgb)
        _check_frame(self.plate)
        self.threshold = float(threshold)
        self.blur = int(blur) | 1
        self._plate_lab = self._lab(self.plate)

    def _lab(self, image: np.ndarray) -> np.ndarray:
        blurred = cv2.GaussianBlur(image, (self.blur, self.blur), 0) if self.blur > 1 else image
        return cv2.cvtColor(blurred, cv2.COLOR_RGB2LAB).astype(np.float32)

    def reset(self) -> None:
        pass

    def __call__(self, frame_rgb, keypoints=None, depth_m=None) -> np.ndarray:
        height, width = _check_frame(frame_rgb)
        if self.plate.shape[:2] != (height, width):
            raise ValueError(
                f"the empty plate is {self.plate.shape[1]}x{self.plate.shape[0]} "
                f"but frames are {width}x{height}"
            )
        difference = self._lab(frame_rgb) - self._plate_lab
        # Lightness counts half: soft shadows change L much more than a and b.
        distance = np.sqrt(0.25 * difference[..., 0] ** 2 + difference[..., 1] ** 2 + difference[..., 2] ** 2)
        return np.where(distance > self.threshold, np.uint8(255), np.uint8(0))


class BackgroundModelMasker:
    """OpenCV's MOG2 or KNN background subtractor; shadows (value 127) count as background."""

    def __init__(self, method: str = "mog2", history: int = 300):
        if method not in ("mog2", "knn"):
            raise ValueError(f"background model must be 'mog2' or 'knn', got {method!r}")
        self.method = method
        self.history = int(history)
        self.reset()

    def reset(self) -> None:
        if self.method == "mog2":
            self._model = cv2.createBackgroundSubtractorMOG2(history=self.history, detectShadows=True)
        else:
            self._model = cv2.createBackgroundSubtractorKNN(history=self.history, detectShadows=True)

    def __call__(self, frame_rgb, keypoints=None, depth_m=None) -> np.ndarray:
        _check_frame(frame_rgb)
        raw = self._model.apply(cv2.cvtColor(frame_rgb, cv2.COLOR_RGB2BGR))
        return np.where(raw == 255, np.uint8(255), np.uint8(0))


class DepthMasker:
    """Keeps pixels whose depth lies within ``slab_m`` of the tracked person's distance.

    Call :meth:`set_depth` with each frame's depth image (metres, aligned to the colour frame,
    0 or NaN = unknown) before the masker; ``depth_m`` is the person's distance (the fitted Th z).
    """

    def __init__(self, slab_m: float = 0.8):
        self.slab_m = float(slab_m)
        self._depth: np.ndarray | None = None

    def reset(self) -> None:
        self._depth = None

    def set_depth(self, depth_m: np.ndarray) -> None:
        self._depth = np.asarray(depth_m, dtype=np.float32)

    def __call__(self, frame_rgb, keypoints=None, depth_m=None) -> np.ndarray:
        height, width = _check_frame(frame_rgb)
        if self._depth is None or depth_m is None or not np.isfinite(depth_m):
            return np.zeros((height, width), np.uint8)
        depth = self._depth
        if depth.shape != (height, width):
            depth = cv2.resize(depth, (width, height), interpolation=cv2.INTER_NEAREST)
        near = np.isfinite(depth) & (depth > 0) & (np.abs(depth - depth_m) < self.slab_m)
        return np.where(near, np.uint8(255), np.uint8(0))


class NoMasker:
    def reset(self) -> None:
        pass

    def __call__(self, frame_rgb, keypoints=None, depth_m=None) -> np.ndarray:
        height, width = _check_frame(frame_rgb)
        return np.zeros((height, width), np.uint8)


def make_masker(method: str, *, plate: np.ndarray | None = None) -> Masker:
    if method not in MASK_METHODS:
        raise ValueError(f"unknown mask method {method!r}; choose one of {', '.join(MASK_METHODS)}")
    if method == "segmentation":
        return SegmentationMasker()
    if method == "plate":
        if plate is None:
            raise ValueError("mask method 'plate' needs an image of the empty scene (--plate FILE)")
        return PlateMasker(plate)
    if method in ("mog2", "knn"):
        return BackgroundModelMasker(method)
    if method == "depth":
        return DepthMasker()
    return NoMasker()


def clean_mask(
    mask: np.ndarray, anchors: np.ndarray | None = None, *, min_area_fraction: float = 0.0005
) -> np.ndarray:
    """Remove specks, close small holes, keep the components that contain an anchor point.

    ``anchors`` (N, 2) image positions of the person's confident keypoints; without anchors every
    component big enough is kept.
    """
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ValueError(f"mask must be (H, W), got {mask.shape}")
    binary = (mask > 0).astype(np.uint8)
    if not binary.any():
        return np.zeros_like(binary, dtype=np.uint8)
    size = max(3, int(round(min(mask.shape) / 160)) | 1)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    binary = cv2.morphologyEx(binary, cv2.MORPH_OPEN, kernel)
    binary = cv2.morphologyEx(binary, cv2.MORPH_CLOSE, kernel, iterations=2)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
    min_area = min_area_fraction * mask.size
    keep = np.zeros(count, dtype=bool)
    if anchors is not None and len(anchors):
        pts = np.round(np.asarray(anchors, dtype=np.float64)).astype(int)
        inside = (
            (pts[:, 0] >= 0) & (pts[:, 0] < mask.shape[1]) & (pts[:, 1] >= 0) & (pts[:, 1] < mask.shape[0])
        )
        hit = labels[pts[inside, 1], pts[inside, 0]]
        keep[np.unique(hit[hit > 0])] = True
    else:
        keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= min_area
    keep[0] = False
    return np.where(keep[labels], np.uint8(255), np.uint8(0))
