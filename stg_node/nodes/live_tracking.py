"""The tracker node's built-in live estimator: camera/frame -> SMPL pose, person mask, confidence.

:class:`TrackingEstimator` is the node's :class:`~stg_node.nodes.estimate.PoseEstimator` backed by
:class:`stg_node.tracking.Tracker` (BlazePose keypoints, SMPL fit, One-Euro smoothing, a mask;
docs/TRACKING.md). The camera comes from each frame: a Tracker is built for the frame's size
and ``K`` (Frame images are undistorted, so no distortion) and built again when either changes.
The tracker's parameters are in the camera's frame; :func:`stg_node.tracking.smpl_to_world`
re-expresses them in the frame's world with the frame's ``R``, ``t``. The smoothing's clock is
the frame's ``time`` (time since the sequence's first frame: from the capture stamps of a live
camera, the media time of a file), so it sees the motion's time gaps, never when a frame happened
to be published (a file replayed as fast as the tracker takes it gave load-dependent poses); a
frame index that goes backwards (a video that loops, a new sequence) is a cut and resets tracking.

Its options (``estimator_params`` of the tracker node) are :class:`LiveTrackingParams`, checked
and coerced like node parameters; they are the :class:`stg_node.tracking.TrackOptions` that
matter when the camera comes with the frames. This module imports the tracking package (torch,
OpenCV, the pose networks) only when the estimator is built, so listing node kinds stays fast.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from typing import Literal

import numpy as np

from stg_node.bus import Frame
from stg_node.nodes.estimate import PoseEstimate
from stg_node.nodes.params import param, parse_params

log = logging.getLogger(__name__)

#: Gap between tracked frames after which the SMPL fit starts afresh (FitConfig.max_temporal_gap_s,
#: 0.5 s for videos). Live, the gap is the tracker's own lag: a fresh start costs 0.4-1 s on this
#: CPU, so with 0.5 s one slow frame makes the next gap too long, and the tracker re-initialises
#: on every frame from then on (a simulated 30 fps camera at 256 px on a busy 2-core box: 27 of
#: 150 frames tracked, every one after the first slow one a fresh start, against 74 with 2 s;
#: docs/BENCHMARKS.md#tracking). A lost person still re-initialises (the detector says so).
LIVE_MAX_GAP_S = 2.0


@dataclass
class LiveTrackingParams:
    smpl_model: str | None = param(
        None, doc="SMPL model file or folder to fit (default: the open body); the trainer's body_model"
    )
    detector: Literal["blazepose", "onnx"] = param("blazepose", doc="keypoint network")
    pose_model: str | None = param(
        None, doc="onnx: the ONNX file; blazepose: a folder with its two .tflite files (default: installed)"
    )
    mask: Literal["segmentation", "plate", "mog2", "knn", "depth", "none"] = param(
        "segmentation",
        doc="person mask: the network's segmentation, an empty plate, a background model, depth",
    )
    plate: str | None = param(None, doc="mask plate: an image of the empty scene at the camera's size")
    max_side: int = param(512, min=0, unit="px", doc="detect and mask on frames scaled to this long side")
    smoothing: bool = param(True, doc="One-Euro smoothing of the parameters over time")
    max_gap_s: float = param(
        LIVE_MAX_GAP_S,
        min=0.0,
        unit="s",
        doc="a longer time since the last tracked frame starts the fit afresh",
    )
    silhouette_weight: float = param(
        0.0,
        min=0.0,
        doc="the fit's silhouette term (FitConfig.silhouette_weight, offline 50): 0 keeps a live "
        "camera's rate; 50 fits joints and orientation better at ~5x the fit's cost",
    )

    def validate(self) -> None:
        if self.max_side != 0 and self.max_side < 64:
            raise ValueError(f"max_side must be 0 (native) or at least 64, got {self.max_side}")
        if self.mask == "plate" and not self.plate:
            raise ValueError("mask plate needs plate (an image of the empty scene)")
        if self.detector == "onnx" and not self.pose_model:
            raise ValueError("detector onnx needs pose_model (the .onnx file)")

    def tracking_settings(self):
        """(FitConfig, TrackOptions) these parameters stand for: the fit's own settings (the gap
        that restarts it, the silhouette term) and the library's track options (the rest)."""
        from stg_node.tracking.fitting import FitConfig
        from stg_node.tracking.pipeline import TrackOptions

        settings = asdict(self)
        fit = FitConfig(
            max_temporal_gap_s=settings.pop("max_gap_s"), silhouette_weight=settings.pop("silhouette_weight")
        )
        return fit, TrackOptions(**settings)


class TrackingEstimator:
    """A PoseEstimator for the tracker node: one :class:`stg_node.tracking.Tracker` per camera setup."""

    def __init__(self, **options):
        self.params = parse_params(LiveTrackingParams, options, where="tracker estimator_params")
        from stg_node.threads import configure_threads

        self.threads = configure_threads()
        self.fit, self.options = self.params.tracking_settings()
        self.tracker = None
        self._camera_key: tuple | None = None
        self._last_index: int | None = None
        # Load the networks and the body now, so a missing file fails the node's setup (exit 1,
        # the message naming the fix) rather than every frame.
        from stg_node.body import load_body_model
        from stg_node.tracking.detectors import make_detector

        load_body_model(self.options.smpl_model)
        make_detector(self.options.detector, model=self.options.pose_model, threads=self.threads)

    def _tracker_for(self, frame: Frame):
        from stg_node.tracking.camera import Intrinsics
        from stg_node.tracking.pipeline import build_tracker

        height, width = frame.image.shape[:2]
        K = np.asarray(frame.K, np.float64)
        key = (width, height, K.tobytes())
        if self.tracker is not None and key == self._camera_key:
            return self.tracker
        if not (K[0, 0] > 0 and K[1, 1] > 0 and np.allclose(K[2], [0.0, 0.0, 1.0])):
            raise ValueError(
                f"frame {frame.index}: K is not a pinhole matrix with positive focal lengths: {K}"
            )
        if self.tracker is not None:
            log.info("the camera changed (%dx%d, K): building the tracker again", width, height)
        intrinsics = Intrinsics(K.copy(), None, width, height, "frame")
        self.tracker, _ = build_tracker(
            self.options, width, height, self.threads, intrinsics=intrinsics, fit=self.fit
        )
        self._camera_key = key
        self._last_index = None
        return self.tracker

    def estimate(self, frame: Frame) -> PoseEstimate:
        from stg_node.tracking.camera import smpl_to_world

        tracker = self._tracker_for(frame)
        if self._last_index is not None and frame.index < self._last_index:
            tracker.reset()  # a cut: do not smooth across it
        self._last_index = frame.index
        if frame.depth is not None and hasattr(tracker.masker, "set_depth"):
            tracker.masker.set_depth(frame.depth)
        estimate = tracker.estimate(np.asarray(frame.image), motion_time(frame))
        smpl = smpl_to_world(estimate.smpl, frame.R, frame.t)
        return PoseEstimate(smpl, float(estimate.confidence), estimate.mask)


def motion_time(frame: Frame) -> float:
    """The frame's time on the motion's clock (seconds): its sequence ``time``; the capture stamp
    where a producer left ``time`` unset (0 after the first frame)."""
    if frame.time <= 0.0 and frame.index > 0 and frame.header.stamp_ns > 0:
        return frame.header.stamp_ns * 1e-9
    return float(frame.time)
