"""Frames a tracker should not trust even when its fit looks right: the person cut by the image
border, or smeared by motion blur.

A fit can explain the keypoints well on a frame an avatar should not learn from:

- **cut by the border**: part of the body is outside the image, so its mask ends at the image
  edge; the keypoints of the missing part are guesses and the pose there is the prior's. The
  test is the length of the person mask along the image border, in units of the person's height
  (``BORDER_CONTACT``: a foot or hand touching the edge is allowed, legs or a head cut off are not).
  Without a mask, a body keypoint (shoulders, hips, knees, ankles, nose) outside the image.
- **motion blur**: the person's texture is smeared; colour learnt from it blurs the avatar. The
  measure is the variance of the Laplacian of the grey image over the person (what a camera's
  autofocus maximises), relative to the same person's recent frames (a striped shirt is sharper
  than a plain one, so only a relative drop means blur): below ``BLUR_RATIO`` of the median of
  the last ``HISTORY`` frames is blurred. The first ``MIN_HISTORY`` frames are never called
  blurred.

Each check that fails multiplies the confidence by its factor (below the trainers' 0.5
threshold, so the frame is skipped) and names a flag (``cut_by_border``, ``motion_blur``).
"""

from __future__ import annotations

from collections import deque

import cv2
import numpy as np

BORDER_CONTACT = 0.05  # mask pixels on the image edge, as a fraction of the person's height
BORDER_FACTOR = 0.2
BLUR_RATIO = 0.35
BLUR_FACTOR = 0.2
HISTORY = 90
MIN_HISTORY = 10
BODY_POINTS = (
    "nose",
    "left_shoulder",
    "right_shoulder",
    "left_hip",
    "right_hip",
    "left_knee",
    "right_knee",
    "left_ankle",
    "right_ankle",
)


def border_contact(mask: np.ndarray) -> float:
    """Pixels of the mask on the image's outermost rows and columns, over the mask's height (0: none)."""
    m = np.asarray(mask) > 0
    if not m.any():
        return 0.0
    rows = np.flatnonzero(m.any(axis=1))
    height = rows[-1] - rows[0] + 1
    edge = int(m[0].sum() + m[-1].sum() + m[1:-1, 0].sum() + m[1:-1, -1].sum())
    return edge / float(height)


def outside(xy: np.ndarray, width: int, height: int) -> np.ndarray:
    """(K,) bool: points outside the ``width x height`` image."""
    xy = np.asarray(xy, np.float64)
    return (xy[:, 0] < -0.5) | (xy[:, 1] < -0.5) | (xy[:, 0] > width - 0.5) | (xy[:, 1] > height - 0.5)


def sharpness(image_rgb: np.ndarray, mask: np.ndarray | None) -> float:
    """Variance of the Laplacian of the grey image over the (slightly shrunk) person mask; NaN without one."""
    grey = cv2.cvtColor(np.asarray(image_rgb), cv2.COLOR_RGB2GRAY)
    lap = cv2.Laplacian(grey, cv2.CV_64F, ksize=3)
    if mask is None:
        return float("nan")
    m = np.asarray(mask) > 0
    if m.shape != grey.shape:
        m = (
            cv2.resize(m.astype(np.uint8), (grey.shape[1], grey.shape[0]), interpolation=cv2.INTER_NEAREST)
            > 0
        )
    m = cv2.erode(m.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0  # not the silhouette's own edge
    if m.sum() < 50:
        return float("nan")
    return float(lap[m].var())


def image_factor(flags) -> float:
    """The confidence factor of a frame's image flags (what :meth:`FrameChecks.check` applied)."""
    factors = {"cut_by_border": BORDER_FACTOR, "motion_blur": BLUR_FACTOR}
    out = 1.0
    for flag in flags:
        out *= factors.get(flag, 1.0)
    return out


class FrameChecks:
    """The border and blur checks of one camera's frames (keeps the recent sharpness)."""

    def __init__(self):
        self.history: deque[float] = deque(maxlen=HISTORY)

    def reset(self) -> None:
        self.history.clear()

    def check(
        self,
        image_rgb: np.ndarray,
        mask: np.ndarray | None,
        keypoints=None,
        layout=None,
    ) -> tuple[float, list[str]]:
        """(confidence factor, flags) for one frame; ``image_rgb`` may be a scaled copy of the frame
        (the mask is resized to it), ``keypoints`` in full-resolution pixels of ``mask``'s size."""
        factor, flags = 1.0, []
        if mask is not None and np.asarray(mask).any():
            cut = border_contact(mask) >= BORDER_CONTACT
        elif keypoints is not None and layout is not None and mask is not None:
            names = [n for n in BODY_POINTS if n in layout.names]
            idx = [layout.index(n) for n in names]
            height, width = np.asarray(mask).shape[:2]
            cut = bool(outside(np.asarray(keypoints.xy)[idx], width, height).any())
        else:
            cut = False
        if cut:
            factor *= BORDER_FACTOR
            flags.append("cut_by_border")
        value = sharpness(image_rgb, mask)
        if np.isfinite(value):
            if len(self.history) >= MIN_HISTORY and value < BLUR_RATIO * float(np.median(self.history)):
                factor *= BLUR_FACTOR
                flags.append("motion_blur")
            else:  # blurred frames do not lower the reference
                self.history.append(value)
        return factor, flags
