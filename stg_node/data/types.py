"""What every dataset yields: one camera view of the person at one instant, with its SMPL pose.

Loaders (ZJU-MoCap, THuman4.0, the folder format, the synthetic benchmark) all produce
these, so the trainer and the evaluation never care where a frame came from. Units and
axes follow docs/ARCHITECTURE.md: metres, seconds, OpenCV cameras with
world-to-camera R, t; images H x W x 3 uint8 RGB; masks H x W uint8 0/255. The SMPL parameters
are :class:`stg_node.body.params.SmplParams` (ZJU-MoCap's ``Rh``/``Th`` convention), the
project's one type for them, re-exported here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stg_node.body.params import SmplParams  # the one SMPL-parameter type; re-exported for loaders

__all__ = ["Camera", "FrameSample", "SmplParams"]


@dataclass(frozen=True)
class Camera:
    """A pinhole camera after undistortion and resizing (OpenCV axes, world-to-camera)."""

    K: np.ndarray  # (3, 3) float64 intrinsics, in pixels of the delivered image
    R: np.ndarray  # (3, 3) float64 rotation, world -> camera
    t: np.ndarray  # (3,) float64 translation, metres
    width: int
    height: int
    name: str = ""


@dataclass(frozen=True)
class FrameSample:
    """One training or evaluation view."""

    index: int  # frame index within the sequence (the pose index)
    time: float  # seconds since the first frame of the sequence
    image: np.ndarray  # (H, W, 3) uint8 RGB, black outside the mask
    mask: np.ndarray  # (H, W) uint8, 255 on the person
    camera: Camera
    smpl: SmplParams
