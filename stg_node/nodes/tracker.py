"""The tracker node: an SMPL body pose for each camera/frame, on body/pose.

Behind the small :class:`PoseEstimator` protocol (``estimate(frame) -> PoseEstimate`` or None),
so a live estimator (images -> SMPL) plugs in where the replay one is today:

- ``mode: replay``: :class:`ReplayEstimator` returns the dataset's own SMPL fit of the frame,
  matched by the frame's index and checked by its time stamp (a frame whose time differs from
  the dataset's time of that index by more than ``max_time_error_s`` is not this dataset's:
  dropped and counted as ``mismatch``).
- ``mode: live``: ``estimator: package.module:Class``, built with ``estimator_params`` as
  keyword arguments, any object with an ``estimate`` method.

Each BodyPose names its frame (``frame_seq``, ``frame_index``) and carries the frame's stamp,
so the trainer pairs them and the renderer's latency counts from the camera.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any, Literal, NamedTuple, Protocol, runtime_checkable

from stg_node.bus import Frame
from stg_node.data.types import SmplParams
from stg_node.nodes.convert import pose_message
from stg_node.nodes.params import param
from stg_node.nodes.runtime import Node


class PoseEstimate(NamedTuple):
    """What an estimator returns for one frame (unpacks as ``smpl, confidence``)."""

    smpl: SmplParams
    confidence: float  # 0..1


@runtime_checkable
class PoseEstimator(Protocol):
    def estimate(self, frame: Frame) -> PoseEstimate | tuple[SmplParams, float] | None:
        """The body in ``frame`` (a camera/frame message: image, K, R, t, index, time), or None
        when there is no person to fit."""


class EstimateMismatch(ValueError):
    """The frame does not belong to the replayed dataset (index unknown or time stamp off)."""


class ReplayEstimator:
    """The dataset's own SMPL parameters for each frame, by index, checked by time stamp."""

    def __init__(self, dataset, max_time_error_s: float = 0.002):
        self.dataset = dataset
        self.frames = set(dataset.all_frames)
        self.max_time_error_s = max_time_error_s

    def estimate(self, frame: Frame) -> PoseEstimate:
        if frame.index not in self.frames:
            raise EstimateMismatch(f"frame index {frame.index} is not in {self.dataset.root}")
        expected = self.dataset.time(frame.index)
        if abs(expected - frame.time) > self.max_time_error_s:
            raise EstimateMismatch(
                f"frame {frame.index} has time {frame.time:.4f} s, "
                f"the dataset's frame {frame.index} is at {expected:.4f} s"
            )
        return PoseEstimate(self.dataset.smpl(frame.index), 1.0)


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
    estimator: str = param("", doc="live: package.module:Class implementing PoseEstimator")
    estimator_params: dict[str, Any] = param({}, doc="live: keyword arguments for the estimator")
    min_confidence: float = param(0.0, min=0.0, max=1.0, doc="drop estimates below this confidence")

    def validate(self) -> None:
        if self.mode == "replay" and not self.path:
            raise ValueError("mode replay needs path (the dataset the ingest node replays)")
        if self.mode == "live" and ":" not in self.estimator:
            raise ValueError("mode live needs estimator: package.module:Class")


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
    if not isinstance(estimator, PoseEstimator):
        raise TypeError(f"{target} has no estimate(frame) method")
    return estimator


class TrackerNode(Node):
    """Publishes body/pose for every camera/frame it receives."""

    kind = "tracker"
    Params = TrackerParams

    def setup(self) -> None:
        p = self.params
        if p.mode == "replay":
            self.estimator: PoseEstimator = ReplayEstimator(
                open_replay_dataset(p.path, p.dataset_kind), p.max_time_error_s
            )
        else:
            self.estimator = load_estimator(p.estimator, p.estimator_params)
        # every frame that reaches us, in order (keep_last=False): a pose per frame for the trainer
        self.subscribe("camera/frame", keep_last=False)
        self._mismatch_logged = False
        self._error_logged = False

    def on_message(self, topic: str, msg) -> None:
        try:
            result = self.estimator.estimate(msg)
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
        smpl, confidence = result
        if confidence < self.params.min_confidence:
            self.drop("low_confidence")
            return
        self.publish(pose_message(smpl, frame=msg, confidence=confidence), stamp_ns=msg.header.stamp_ns)
