"""Rigs of several cameras on the bus: one topic per camera, and the tracker's multi-view estimator.

Topics. Each camera of a rig (rig.json, docs/RIGS.md) has its own frame and pose topics, the
camera's name put in front of the standard name: ``camera/frame`` -> ``front/camera/frame``,
``raw/camera/frame`` -> ``raw/front/camera/frame``, ``body/pose`` -> ``front/body/pose``
(:func:`camera_topic`). They keep the standard name at their end, so they ride its lane, and a
keep-last subscriber keeps the newest frame of *each* camera, not of the rig. The rig ingest
publishes frames there; the tracker (``rig: rig.json``) reads them, matches the cameras' frames
by capture stamp, tracks the set, and republishes every view with its mask on the camera's
``camera/frame`` topic with a BodyPose naming it on the camera's ``body/pose`` (seq numbers count
per topic, so a pose and its frame are paired within one camera), the same world-frame
parameters for every camera; and one more BodyPose on plain ``body/pose`` (naming the first
camera's frame) for whoever wants the body, not a view: the renderer. The trainer
(``rig: rig.json``) reads every camera's frame and pose topics.

Every view of a set carries the first camera's frame index and time (one instant, one index: the
trainer's per-frame pose refinement and optical flow rely on it).

:class:`RigTrackingEstimator` is the tracker's built-in multi-view estimator: a
:class:`stg_node.tracking.multiview.MultiViewTracker` for the frames' cameras (undistorted pinhole
``K``, world-to-camera ``R``, ``t`` as the frames carry them), options as the single-camera
estimator's (:class:`~stg_node.nodes.live_tracking.LiveTrackingParams`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stg_node.bus import Frame
from stg_node.nodes.params import parse_params

log = logging.getLogger(__name__)

STANDARD = ("camera/frame", "body/pose")


def camera_topic(topic: str, camera: str) -> str:
    """The topic of one camera of a rig: its name before the standard name (module docstring)."""
    for standard in STANDARD:
        if topic.endswith(standard):
            return f"{topic[: -len(standard)]}{camera}/{standard}"
    return f"{topic}/{camera}"


def rig_subscriptions(node, names: list[str]):
    """A node's subscriptions to every camera's frame and pose topics, and ``camera_of(msg)``."""
    frame_topics = [camera_topic("camera/frame", n) for n in names]
    pose_topics = [camera_topic("body/pose", n) for n in names]
    frames = node.subscribe(*frame_topics)  # keep-last per camera
    poses = node.subscribe(*pose_topics)
    full = {
        node.bus.config.topic(node.topic(t)): n
        for t, n in zip(frame_topics + pose_topics, names + names, strict=True)
    }
    return frames, poses, lambda msg: full.get(msg.header.topic, "")


def rig_camera_names(path: str | Path) -> list[str]:
    """The camera names of a rig.json, in order (checked: stg_node.calibration.rig)."""
    from stg_node.calibration.rig import read_rig

    return read_rig(path).names


@dataclass(frozen=True)
class RigEstimate:
    """What a rig estimator returns for one set of frames."""

    smpl: object  # SmplParams in the rig's world frame
    confidence: float
    masks: list  # per camera, (H, W) uint8 or None


class RigTrackingEstimator:
    """The tracker node's built-in multi-view estimator (see the module docstring)."""

    def __init__(self, **options):
        from stg_node.nodes.live_tracking import LiveTrackingParams

        self.params = parse_params(LiveTrackingParams, options, where="tracker estimator_params")
        from stg_node.threads import configure_threads

        if self.params.mask in ("plate", "depth"):
            raise ValueError(
                f"mask {self.params.mask!r} is not available for a rig (segmentation, mog2, knn, none)"
            )
        self.threads = configure_threads()
        # The rig's multi-view fit has no silhouette term (the parameter is the single camera's).
        self.fit, self.options = self.params.tracking_settings()
        self.tracker = None
        self._key: tuple | None = None
        self._last_index: int | None = None
        from stg_node.body import load_body_model
        from stg_node.tracking.detectors import make_detector

        self.body = load_body_model(self.options.smpl_model)
        make_detector(self.options.detector, model=self.options.pose_model, threads=self.threads)

    def _tracker_for(self, frames: list[Frame]):
        from stg_node.calibration.rig import Rig, RigCamera
        from stg_node.tracking.detectors import make_detector
        from stg_node.tracking.masks import make_masker
        from stg_node.tracking.multiview import MultiViewConfig, MultiViewTracker

        key = tuple(
            (f.camera_id, f.image.shape, np.asarray(f.K).tobytes(), np.asarray(f.R).tobytes()) for f in frames
        )
        if self.tracker is not None and key == self._key:
            return self.tracker
        cameras = []
        for frame in frames:
            height, width = frame.image.shape[:2]
            cameras.append(
                RigCamera(
                    frame.camera_id,
                    np.asarray(frame.K, np.float64),
                    np.zeros(0),
                    np.asarray(frame.R, np.float64),
                    np.asarray(frame.t, np.float64).reshape(3),
                    (width, height),
                )
            )
        rig = Rig(tuple(cameras))
        if self.tracker is not None:
            log.info("the rig's cameras changed: building the multi-view tracker again")
        detectors = [
            make_detector(self.options.detector, model=self.options.pose_model, threads=self.threads)
            for _ in frames
        ]
        maskers = [make_masker(self.options.mask_method()) for _ in frames]
        config = MultiViewConfig(
            max_side=self.options.max_side, smoothing=self.options.smoothing, fit=self.fit
        )
        self.tracker = MultiViewTracker(detectors, self.body, rig, config, maskers)
        self._key = key
        self._last_index = None
        return self.tracker

    def estimate_set(self, frames: list[Frame]) -> RigEstimate:
        tracker = self._tracker_for(frames)
        index = frames[0].index
        if self._last_index is not None and index < self._last_index:
            tracker.reset()  # a cut (a looping replay): do not smooth across it
        self._last_index = index
        stamp_ns = frames[0].header.stamp_ns
        timestamp = stamp_ns * 1e-9 if stamp_ns > 0 else float(frames[0].time)
        estimate = tracker.estimate([np.asarray(f.image) for f in frames], timestamp)
        return RigEstimate(estimate.smpl, float(estimate.confidence), list(estimate.masks))


class RigTracking:
    """The tracker node's rig mode (see the module docstring): per-camera subscriptions, stamp
    matching, one estimate per complete set, a frame and a pose per camera published."""

    def __init__(self, node, estimator):
        from stg_node.tracking.sync import StampMatcher

        if not hasattr(estimator, "estimate_set"):
            raise TypeError(
                f"{type(estimator).__name__} has no estimate_set(frames) method: not a rig estimator"
            )
        p = node.params
        self.node = node
        self.estimator = estimator
        self.names = rig_camera_names(p.rig)
        self.topics = {camera_topic(p.input_topic, name): name for name in self.names}
        latest_only = True if p.latest_only is None else p.latest_only
        for topic in self.topics:
            node.subscribe(topic, keep_last=latest_only)
        self.matcher = StampMatcher(self.names, int(round(p.sync_tolerance_s * 1e9)))
        self.unmatched = 0
        self.sets = 0
        self._error_logged = False
        node.log.info(
            "rig of %d cameras (%s): frames from %s",
            len(self.names),
            ", ".join(self.names),
            ", ".join(self.topics),
        )

    def on_frame(self, topic: str, msg: Frame) -> None:
        from stg_node.nodes.convert import pose_message

        node, p = self.node, self.node.params
        name = self.topics.get(topic)
        if name is None:
            node.drop("unknown_camera")
            return
        stamp = msg.header.stamp_ns if msg.header.stamp_ns > 0 else int(round(float(msg.time) * 1e9))
        done = self.matcher.push(name, stamp, msg)
        if self.matcher.incomplete > self.unmatched:  # frames no other camera's matched in time
            node.drop("unmatched", self.matcher.incomplete - self.unmatched)
            self.unmatched = self.matcher.incomplete
        if done is None:
            return
        _, by_camera = done
        frames = [by_camera[n] for n in self.names]
        try:
            result = self.estimator.estimate_set(frames)
        except Exception as exc:  # one bad set must not end the tracker
            node.drop("estimator_error")
            node.error(f"rig estimator failed on frame {frames[0].index}: {exc!r}")
            if not self._error_logged:
                node.log.exception("rig estimator failed on frame %d (logged once)", frames[0].index)
                self._error_logged = True
            return
        if result is None:
            node.drop("no_person")
            return
        if result.confidence < p.min_confidence:
            node.drop("low_confidence")
            return
        self.sets += 1
        leader = frames[0]
        masks = list(result.masks) if result.masks is not None else [None] * len(frames)
        for name, frame, mask in zip(self.names, frames, masks, strict=True):
            sent = frame
            if p.frame_topic:
                sent = Frame(
                    index=leader.index,  # one instant, one index
                    time=leader.time,
                    camera_id=name,
                    image=frame.image,
                    mask=mask if mask is not None else frame.mask,
                    depth=frame.depth,
                    K=frame.K,
                    R=frame.R,
                    t=frame.t,
                )
                sent.header.seq = node.publish(
                    sent, camera_topic(p.frame_topic, name), stamp_ns=frame.header.stamp_ns
                )
            pose = pose_message(result.smpl, frame=sent, confidence=result.confidence)
            node.publish(pose, camera_topic("body/pose", name), stamp_ns=leader.header.stamp_ns)
            if name == self.names[0]:
                node.publish(pose, stamp_ns=leader.header.stamp_ns)  # the body, for the renderer
