"""Bus messages <-> the data types the avatar and the datasets use (Camera, SmplParams, FrameSample).

One place for the field-by-field copies between ``stg_node.bus`` messages (wire types) and
``stg_node.data.types`` (what loaders yield and the avatar consumes), so no node spells them out.
Poses go through the bus's own conversion (``BodyPose.from_smpl`` / ``BodyPose.to_smpl``).
"""

from __future__ import annotations

import numpy as np

from stg_node.bus import BodyPose, Frame, ViewRequest
from stg_node.data.types import Camera, FrameSample, SmplParams

DEFAULT_NUM_BETAS = 10


def frame_message(sample: FrameSample, *, camera_id: str = "") -> Frame:
    """A camera/frame message of a dataset view (image, mask, calibration, index, time)."""
    cam = sample.camera
    return Frame(
        index=int(sample.index),
        time=float(sample.time),
        camera_id=camera_id or cam.name,
        image=np.ascontiguousarray(sample.image),
        mask=None if sample.mask is None else np.ascontiguousarray(sample.mask),
        K=np.asarray(cam.K, np.float64),
        R=np.asarray(cam.R, np.float64),
        t=np.asarray(cam.t, np.float64).reshape(3),
    )


def frame_camera(frame: Frame) -> Camera:
    h, w = frame.image.shape[:2]
    return Camera(
        K=np.array(frame.K), R=np.array(frame.R), t=np.array(frame.t), width=w, height=h, name=frame.camera_id
    )


def pose_message(smpl: SmplParams, *, frame: Frame | None = None, confidence: float = 1.0) -> BodyPose:
    """A body/pose message for ``smpl``, tied to ``frame`` (its seq, index and time) when given."""
    return BodyPose.from_smpl(
        smpl,
        frame_seq=frame.header.seq if frame is not None and frame.header.seq >= 0 else -1,
        frame_index=frame.index if frame is not None else -1,
        time=frame.time if frame is not None else 0.0,
        confidence=float(confidence),
    )


def request_camera(request: ViewRequest) -> Camera:
    return Camera(
        K=np.array(request.K),
        R=np.array(request.R),
        t=np.array(request.t),
        width=request.width,
        height=request.height,
    )


def request_smpl(request: ViewRequest, betas: np.ndarray | None) -> SmplParams:
    """The pose a one-shot request asks for; the shape (betas) is the live body's, else zeros."""
    zeros3 = np.zeros(3, np.float32)
    return SmplParams(
        poses=np.array(request.poses, np.float32),
        Rh=np.array(request.Rh if request.Rh is not None else zeros3, np.float32),
        Th=np.array(request.Th if request.Th is not None else zeros3, np.float32),
        betas=np.array(betas if betas is not None else np.zeros(DEFAULT_NUM_BETAS), np.float32),
    )


def resized_camera(camera: Camera, size: int) -> Camera:
    """``camera`` scaled so its longer side is ``size`` pixels (same field of view)."""
    scale = size / max(camera.width, camera.height)
    if abs(scale - 1.0) < 1e-9:
        return camera
    K = np.array(camera.K, np.float64)
    K[:2] *= scale
    width = max(1, round(camera.width * scale))
    height = max(1, round(camera.height * scale))
    return Camera(K=K, R=camera.R, t=camera.t, width=width, height=height, name=camera.name)
