"""The tracker node: an SMPL body pose for each camera/frame, on body/pose (and the person mask).

Behind the small :class:`PoseEstimator` protocol (``estimate(frame) -> PoseEstimate`` or None):

- ``mode: replay``: :class:`ReplayEstimator` returns the dataset's own SMPL fit of the frame,
  matched by the frame's index and checked by its time stamp (a frame whose time differs from
  the dataset's time of that index by more than ``max_time_error_s`` is not this dataset's:
  dropped and counted as ``mismatch``). SMPL-X fits (THuman4.0) are sent as their nearest SMPL
  parameters (:func:`stg_node.body.params.smplx_as_smpl`: the shared joints, the mean shape).
- ``mode: live``: an estimator that looks at the image. By default the built-in one,
  :class:`stg_node.nodes.live_tracking.TrackingEstimator` (BlazePose + SMPL fit + smoothing +
  a person mask, ``stg_node.tracking``), configured by ``estimator_params``; or
  ``estimator: package.module:Class``, built with ``estimator_params`` as keyword arguments,
  any object with an ``estimate`` method.

Each BodyPose names its frame (``frame_seq``, ``frame_index``), carries the frame's stamp and the
estimator's confidence, so the trainer pairs them (and skips unsure ones) and the renderer's
latency counts from the camera.

A rig of several cameras (``rig: rig.json``, ``mode: live``; docs/RIGS.md): the node reads each
camera's own topic (:func:`stg_node.nodes.rig.camera_topic` of ``input_topic``), pairs the
cameras' frames by capture stamp (within ``sync_tolerance_s``; :class:`stg_node.tracking.sync
.StampMatcher`), tracks each complete set with a multi-view estimator (default
:class:`stg_node.nodes.rig.RigTrackingEstimator`, or ``estimator`` with an ``estimate_set(frames)``
method) and publishes, per camera, the frame with its mask on that camera's ``frame_topic`` and a
BodyPose naming it, in the rig's world frame.

The person mask travels where proto/ puts it, in a Frame (BodyPose has no image-sized arrays):
with ``frame_topic`` set, the tracker republishes each frame it tracked, with the estimator's
mask, on that topic, and the pose names that message. The live launch files remap the ingest's
output to ``raw/camera/frame`` and give the tracker ``input_topic: raw/camera/frame,
frame_topic: camera/frame``, so everything downstream reads camera/frame as in a replay, now
with masks (docs/NODES.md, "tracker").
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from stg_node.bus import Frame
from stg_node.nodes.convert import pose_message
from stg_node.nodes.estimate import PoseEstimate, PoseEstimator, as_estimate
from stg_node.nodes.params import param
from stg_node.nodes.runtime import Node

#: The estimator ``mode: live`` uses when ``estimator`` is empty.
BUILTIN_ESTIMATOR = "stg_node.nodes.live_tracking:TrackingEstimator"
#: The same with a ``rig``.
BUILTIN_RIG_ESTIMATOR = "stg_node.nodes.rig:RigTrackingEstimator"


class EstimateMismatch(ValueError):
    """The frame does not belong to the replayed dataset (index unknown or time stamp off)."""


class ReplayEstimator:
    """The dataset's own SMPL parameters for each frame, by index, checked by time stamp."""

    def __init__(self, dataset, max_time_error_s: float = 0.002, log=None):
        self.dataset = dataset
        self.frames = set(dataset.all_frames)
        self.max_time_error_s = max_time_error_s
        self.log = log
        self.converted = 0  # SMPL-X fits sent as SMPL

    def estimate(self, frame: Frame) -> PoseEstimate:
        from stg_node.body.params import smplx_as_smpl

        if frame.index not in self.frames:
            raise EstimateMismatch(f"frame index {frame.index} is not in {self.dataset.root}")
        expected = self.dataset.time(frame.index)
        if abs(expected - frame.time) > self.max_time_error_s:
            raise EstimateMismatch(
                f"frame {frame.index} has time {frame.time:.4f} s, "
                f"the dataset's frame {frame.index} is at {expected:.4f} s"
            )
        smpl = self.dataset.smpl(frame.index)
        if smpl.model != "smpl":
            if not self.converted and self.log is not None:
                self.log.warning(
                    "%s ships %s fits: sending the nearest SMPL parameters (the 22 shared joints; "
                    "SMPL-X betas dropped for SMPL's mean shape; see docs/NODES.md, tracker)",
                    self.dataset.root,
                    smpl.model.upper(),
                )
            self.converted += 1
            smpl = smplx_as_smpl(smpl)
        return PoseEstimate(smpl, 1.0)


@dataclass
class TrackerParams:
    mode: Literal["replay", "live"] = param("replay", doc="replay a dataset's SMPL fits, or a live estimator")
    path: str = param("", doc="replay: the dataset folder the ingest node replays")
    dataset_kind: Literal["auto", "zju", "thuman4", "folder", "synth"] = param(
        "auto", doc="replay: dataset layout"
    )
    max_time_error_s: float = param(
        0.002, min=0.0, unit="s", doc="replay: frame time vs dataset time tolerance"
    )
    estimator: str = param(
        "", doc="live: package.module:Class implementing PoseEstimator (empty: the built-in tracker)"
    )
    estimator_params: dict[str, Any] = param(
        {}, doc="live: keyword arguments for the estimator (the built-in one's: table below)"
    )
    min_confidence: float = param(
        0.0, min=0.0, max=1.0, doc="drop estimates below this confidence (the trainer has its own threshold)"
    )
    input_topic: str = param("camera/frame", doc="the frames to track")
    frame_topic: str = param(
        "", doc="republish each tracked frame with the estimator's person mask here (empty: off)"
    )
    latest_only: bool | None = param(
        None, doc="track only the newest frame (no backlog) or every frame in order; default: live yes"
    )
    # several cameras (docs/RIGS.md)
    rig: str = param("", doc="live: a rig.json: track its cameras together, each on its own topic")
    sync_tolerance_s: float = param(
        0.02, min=0.0, unit="s", doc="rig: frames of one instant lie within this of each other's stamps"
    )

    def validate(self) -> None:
        if self.rig and self.mode != "live":
            raise ValueError("rig needs mode live")
        if self.mode == "replay" and not self.path:
            raise ValueError("mode replay needs path (the dataset the ingest node replays)")
        if self.mode == "live" and self.estimator and ":" not in self.estimator:
            raise ValueError("estimator must look like package.module:Class (empty: the built-in tracker)")
        if self.frame_topic and self.frame_topic == self.input_topic:
            raise ValueError(f"frame_topic and input_topic are both {self.input_topic!r}: a loop")


def open_replay_dataset(path: str, kind: str = "auto"):
    """The dataset whose SMPL fits are replayed (smpl(i) reads any frame)."""
    from pathlib import Path

    from stg_node.data import open_dataset

    root = Path(path)
    if (root / "synth.json").is_file() and kind in ("auto", "synth"):
        from stg_node.data.synth.dataset import open_synth

        return open_synth(root, "train", size=None)
    return open_dataset(root, "auto" if kind == "synth" else kind, "train", size=None)


def load_estimator(target: str, options: dict) -> PoseEstimator:
    module_name, _, class_name = target.partition(":")
    cls = getattr(importlib.import_module(module_name), class_name)
    estimator = cls(**options)
    if not isinstance(estimator, PoseEstimator) and not hasattr(estimator, "estimate_set"):
        raise TypeError(f"{target} has no estimate(frame) (or, for a rig, estimate_set(frames)) method")
    return estimator


class TrackerNode(Node):
    """Publishes body/pose for every camera/frame it receives (and the frame with its mask)."""

    kind = "tracker"
    Params = TrackerParams

    def setup(self) -> None:
        p = self.params
        self.rig = None
        if p.rig:
            from stg_node.nodes.rig import RigTracking

            self.rig = RigTracking(
                self, load_estimator(p.estimator or BUILTIN_RIG_ESTIMATOR, p.estimator_params)
            )
            return
        if p.mode == "replay":
            self.estimator: PoseEstimator = ReplayEstimator(
                open_replay_dataset(p.path, p.dataset_kind), p.max_time_error_s, self.log
            )
        else:
            self.estimator = load_estimator(p.estimator or BUILTIN_ESTIMATOR, p.estimator_params)
        latest_only = p.mode == "live" if p.latest_only is None else p.latest_only
        # replay: every frame, in order (a pose per frame for the trainer; the ingest paces);
        # live: the newest frame, so a tracker slower than the camera lags by one frame, not a queue
        self.subscribe(p.input_topic, keep_last=latest_only)
        self._mismatch_logged = False
        self._error_logged = False

    def on_message(self, topic: str, msg) -> None:
        if self.rig is not None:
            self.rig.on_frame(topic, msg)
            return
        try:
            result = as_estimate(self.estimator.estimate(msg))
        except EstimateMismatch as exc:
            self.drop("mismatch")
            if not self._mismatch_logged:
                self.log.warning("%s (logged once; counted as drops.mismatch)", exc)
                self._mismatch_logged = True
            return
        except Exception as exc:  # one bad frame must not end the tracker
            self.drop("estimator_error")
            self.error(f"estimator failed on frame {msg.index}: {exc!r}")
            if not self._error_logged:
                self.log.exception("estimator failed on frame %d (logged once)", msg.index)
                self._error_logged = True
            return
        if result is None:
            self.drop("no_person")
            return
        if result.confidence < self.params.min_confidence:
            self.drop("low_confidence")
            return
        frame = msg
        if self.params.frame_topic:
            frame = self._republish(msg, result.mask)
        self.publish(
            pose_message(result.smpl, frame=frame, confidence=result.confidence),
            stamp_ns=msg.header.stamp_ns,
        )

    def _republish(self, msg: Frame, mask: np.ndarray | None) -> Frame:
        """``msg`` with the estimator's mask (else its own) on ``frame_topic``; the sent Frame, whose
        header carries the seq the pose must name."""
        frame = Frame(
            index=msg.index,
            time=msg.time,
            camera_id=msg.camera_id,
            image=msg.image,
            mask=mask if mask is not None else msg.mask,
            depth=msg.depth,
            K=msg.K,
            R=msg.R,
            t=msg.t,
        )
        frame.header.seq = self.publish(frame, self.params.frame_topic, stamp_ns=msg.header.stamp_ns)
        return frame
