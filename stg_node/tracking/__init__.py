"""Live tracking: SMPL pose, shape and a person mask per frame of a plain camera or video (docs/TRACKING.md).

Public interface:

- :class:`PoseEstimator` (protocol): ``estimate(frame_rgb, timestamp) -> TrackEstimate`` (SMPL
  parameters in the camera's frame, an (H, W) uint8 mask, a confidence in [0, 1]) and ``reset()``;
  :class:`Tracker` is the implementation (detector -> SMPL fit -> One-Euro smoothing -> mask).
- :func:`make_detector`: the keypoint networks (``blazepose``: MediaPipe's BlazePose under
  LiteRT, installed at setup; ``onnx``: a COCO-17 model the user supplies), pluggable through
  the :class:`KeypointDetector` protocol.
- :func:`track_to_file` / :func:`track_video` (cached): a video file or image folder -> POSES.npz
  (the format ``stg-track`` writes: poses_file.py) and masks; :func:`video_to_folder`: the same
  as a folder-format dataset of the confident frames, for ``stg-train --format video``.
- Several calibrated cameras (docs/RIGS.md): :class:`MultiViewTracker` (one instant of a rig ->
  SMPL in its world frame), :func:`track_rig_to_file` / :func:`track_rig` / :func:`rig_to_folder`
  (rig_pipeline.py: a rig's recordings, matched by time stamp: sync.py).

Where it sits: it uses ``body`` (the body model, LBS), ``data`` (types, readers, the synthetic
benchmark's joint limits) and the foundation helpers (progress, threads); it knows nothing of
the bus or the node runtime. ``cli`` (``stg-track``) and the tracker node call it.
"""

from stg_node.tracking.camera import DEFAULT_FOV_DEG, Intrinsics, from_fov, load_intrinsics, smpl_to_world
from stg_node.tracking.detectors import KeypointDetector, make_detector
from stg_node.tracking.fitting import FitConfig, SmplFitter
from stg_node.tracking.multiview import MultiViewConfig, MultiViewEstimate, MultiViewTracker
from stg_node.tracking.pipeline import (
    TrackOptions,
    build_tracker,
    track_to_file,
    track_video,
    video_to_folder,
)
from stg_node.tracking.poses_file import TrackedPoses, read_poses, write_poses
from stg_node.tracking.rig_pipeline import rig_to_folder, track_rig, track_rig_to_file
from stg_node.tracking.tracker import Tracker, TrackerConfig
from stg_node.tracking.types import Keypoints, PoseEstimator, SmplParams, TrackEstimate

__all__ = [
    "DEFAULT_FOV_DEG",
    "FitConfig",
    "Intrinsics",
    "KeypointDetector",
    "Keypoints",
    "MultiViewConfig",
    "MultiViewEstimate",
    "MultiViewTracker",
    "PoseEstimator",
    "SmplFitter",
    "SmplParams",
    "TrackEstimate",
    "TrackOptions",
    "TrackedPoses",
    "Tracker",
    "TrackerConfig",
    "build_tracker",
    "from_fov",
    "load_intrinsics",
    "make_detector",
    "read_poses",
    "rig_to_folder",
    "smpl_to_world",
    "track_rig",
    "track_rig_to_file",
    "track_to_file",
    "track_video",
    "video_to_folder",
    "write_poses",
]
