"""What every dataset yields: one camera view of the person at one instant, with its SMPL pose.

Loaders (ZJU-MoCap, THuman4.0, the folder format, the synthetic benchmark) all produce
these, so the trainer and the evaluation never care where a frame came from. Units and
axes follow ../shared/ARCHITECTURE.md: metres, seconds, OpenCV cameras with
world-to-camera R, t; images H x W x 3 uint8 RGB; masks H x W uint8 0/255.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SmplParams:
    """SMPL parameters of one frame in ZJU-MoCap's convention.

    world_vertices = rotation(Rh) @ smpl(betas, poses) + Th, where ``poses[0]`` is SMPL's own
    global orientation (often zero in ZJU-MoCap, which puts it in ``Rh`` instead).
    """

    poses: np.ndarray  # (24, 3) axis-angle per joint, radians, float32
    Rh: np.ndarray  # (3,) axis-angle global rotation, float32
    Th: np.ndarray  # (3,) global translation, metres, float32
    betas: np.ndarray  # (num_betas,) shape coefficients, float32
    # Which body model the parameters belong to: "smpl", or "smplx" where a dataset only ships
    # SMPL-X fits (THuman4.0): the 22 shared joints map over, but SMPL-X betas span another space.
    model: str = "smpl"


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
