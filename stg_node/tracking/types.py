"""What the tracker passes around: detected keypoints, one frame's estimate, the estimator protocol.

The SMPL parameter container is imported here and nowhere else in the package, so moving it
(to ``stg_node.body.params``) is a one-line change.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from stg_node.body.params import SmplParams

__all__ = ["Keypoints", "PoseEstimator", "SmplParams", "TrackEstimate"]


@dataclass(frozen=True)
class Keypoints:
    """2D body keypoints of one person in one image, in a named layout (see layouts.py)."""

    layout: str  # e.g. "blazepose33", "coco17", "smpl24"
    xy: np.ndarray  # (K, 2) float32 image pixels (pixel (r, c) has its centre at (c, r))
    score: np.ndarray  # (K,) float32 in [0, 1]: how much to trust each point (0 = missing)
    world: np.ndarray | None = (
        None  # (K, 3) metres, root-relative, camera-aligned axes, if the network gives it
    )
    presence: float = 1.0  # the detector's belief that a person is there at all
    people: int = 1  # people the detector saw in the frame (when it last looked)
    segmentation: np.ndarray | None = None  # (H, W) float32 person probability, if the network gives it

    def __post_init__(self):
        xy = np.asarray(self.xy)
        score = np.asarray(self.score)
        if xy.ndim != 2 or xy.shape[1] != 2 or score.shape != (xy.shape[0],):
            raise ValueError(f"keypoints need xy (K, 2) and score (K,), got {xy.shape} and {score.shape}")
        if self.world is not None and np.asarray(self.world).shape != (xy.shape[0], 3):
            raise ValueError(
                f"world keypoints must be ({xy.shape[0]}, 3), got {np.asarray(self.world).shape}"
            )


@dataclass(frozen=True)
class TrackEstimate:
    """One frame's answer: SMPL parameters in the camera's frame, the person mask, a confidence."""

    smpl: SmplParams  # poses (24, 3) with poses[0] = 0, Rh/Th in the camera frame (OpenCV axes)
    mask: np.ndarray  # (H, W) uint8, 255 on the person
    confidence: float  # [0, 1]; the trainer skips frames below its threshold
    timestamp: float  # seconds, as given
    keypoints: Keypoints | None = None  # what the fit used (None when no person was found)
    reprojection_px: float = float("nan")  # weighted RMS keypoint residual of the fit, pixels
    flags: tuple[str, ...] = field(default_factory=tuple)  # why confidence is low: "no_person", ...


@runtime_checkable
class PoseEstimator(Protocol):
    """Anything that turns a camera frame into SMPL parameters, a mask and a confidence.

    ``estimate`` is called once per frame, in time order; implementations keep state between
    calls (tracking, smoothing) and ``reset`` forgets it (a cut in the video).
    """

    def estimate(self, frame_rgb: np.ndarray, timestamp: float) -> TrackEstimate: ...

    def reset(self) -> None: ...
