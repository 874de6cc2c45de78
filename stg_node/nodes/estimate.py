"""What a tracker node's estimator returns, and the interface it implements.

Its own module so that estimators (live_tracking.py, rig.py) and the tracker node that loads them
by name can all import it without importing each other.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from stg_node.bus import Frame
from stg_node.data.types import SmplParams

__all__ = ["PoseEstimate", "PoseEstimator", "as_estimate"]


@dataclass(frozen=True)
class PoseEstimate:
    """What an estimator returns for one frame."""

    smpl: SmplParams  # in the frame's world (the Frame's R, t map it into the camera)
    confidence: float  # 0..1
    mask: np.ndarray | None = None  # (H, W) uint8 0/255 person mask of the frame, if the estimator makes one


@runtime_checkable
class PoseEstimator(Protocol):
    def estimate(self, frame: Frame) -> PoseEstimate | tuple[SmplParams, float] | None:
        """The body in ``frame`` (a camera/frame message: image, K, R, t, index, time), or None
        when there is no person to fit. A plain ``(smpl, confidence)`` pair is accepted too."""


def as_estimate(result) -> PoseEstimate | None:
    """An estimator's answer as a PoseEstimate (None stays None); TypeError for anything else."""
    if result is None or isinstance(result, PoseEstimate):
        return result
    if isinstance(result, tuple) and len(result) == 2 and isinstance(result[0], SmplParams):
        return PoseEstimate(result[0], float(result[1]))
    raise TypeError(
        f"an estimator returns PoseEstimate, (SmplParams, confidence) or None, got {type(result).__name__}"
    )
