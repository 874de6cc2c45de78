"""The ingest node: images with calibration (and a mask when the data has one) on camera/frame.

Sources (:mod:`.sources`): a dataset split (ZJU-MoCap, THuman4.0, stg-synth output, folder
format), a video file, a V4L2 camera, an OAK camera (or a video file through depthai's host-side
replay), a rig of several cameras (``source: rig``, :mod:`.rig_sources`: V4L2 devices or video
files, each frame stamped at capture and published on its camera's own topic, ``NAME/camera/frame``
under the remapped name: :mod:`.rig`). Pacing (``rate_hz``): -1 the source's own rate (dataset
fps, file fps, a live camera as it delivers), > 0 that rate, 0 as fast as consumers take it:
frame k waits until a message on ``pace_topic`` (the tracker's body/pose, which names its frame)
acknowledges frame k - ``max_ahead``, or ``pace_timeout_s`` passes.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Literal

from stg_node.bus import Frame
from stg_node.nodes.params import param
from stg_node.nodes.runtime import Node
from stg_node.nodes.sources import CapturedFrame, SourceError


@dataclass
class IngestParams:
    source: Literal["dataset", "video", "v4l2", "oak", "rig"] = param("dataset", doc="where frames come from")
    path: str = param("", doc="dataset folder or video file (oak: a video file replays through depthai)")
    dataset_kind: Literal["auto", "zju", "thuman4", "folder", "synth"] = param("auto", doc="dataset layout")
    split: str = param("train", doc="dataset split: train, novel_view, novel_pose, all")
    camera: str = param("", doc="only this dataset camera (default: every camera of the split)")
    train_frames: str = param(
        "", doc="ZJU-MoCap: the training range START:STOP[:STEP] (default: the subject's)"
    )
    size: int = param(512, min=0, doc="dataset images: longer side in pixels (0: native)")
    device: str = param("0", doc="v4l2: device index or /dev/videoN")
    width: int = param(0, min=0, unit="px", doc="live/video frame width (0: the source's)")
    height: int = param(0, min=0, unit="px", doc="live/video frame height (0: the source's)")
    fps: float = param(0.0, min=0.0, unit="Hz", doc="live capture rate to ask for (0: the source's)")
    calibration: str = param("", doc="live/video: JSON with K (and R, t) for the delivered size")
    hfov_deg: float = param(
        60.0, min=1.0, max=179.0, unit="deg", doc="live/video without calibration: field of view"
    )
    rate_hz: float = param(
        -1.0, min=-1.0, unit="Hz", doc="-1 the source's rate, 0 as fast as consumed, > 0 fixed"
    )
    pace_topic: str = param("body/pose", doc="rate_hz 0: the topic whose frame_seq acknowledges frames")
    max_ahead: int = param(2, min=0, doc="rate_hz 0: frames published ahead of the last acknowledged one")
    pace_timeout_s: float = param(2.0, min=0.0, unit="s", doc="rate_hz 0: publish anyway after this long")
    loop: bool = param(False, doc="start over at the end (dataset and video sources)")
    max_frames: int = param(0, min=0, doc="stop after this many frames (0: no limit)")
    wait_subscribers_s: float = param(
        5.0, min=0.0, unit="s", doc="before the first frame, wait this long for a subscriber"
    )
    # source rig (docs/RIGS.md): several cameras, one topic each
    rig: str = param("", doc="rig: the rig.json (stg-calibrate) whose cameras the devices are")
    devices: str = param("", doc="rig: V4L2 devices, one per rig camera in its order, comma-separated")
    videos: str = param("", doc="rig without cameras: video files, one per rig camera, played together")

    def validate(self) -> None:
        if self.source in ("dataset", "video") and not self.path:
            raise ValueError(f"source {self.source!r} needs a path")
        if self.source == "rig" and (not self.rig or bool(self.devices) == bool(self.videos)):
            raise ValueError("source rig needs rig (a rig.json) and either devices or videos")


class IngestNode(Node):
    """Publishes camera/frame from a dataset, a video file, a V4L2 or an OAK camera."""

    kind = "ingest"
    Params = IngestParams

    def setup(self) -> None:
        p = self.params
        from stg_node.nodes import sources

        try:
            if p.source == "dataset":
                self.source = sources.DatasetSource(
                    p.path,
                    kind=p.dataset_kind,
                    split=p.split,
                    size=p.size or None,
                    camera=p.camera,
                    train_frames=p.train_frames,
                )
            elif p.source in ("video", "v4l2"):
                self.source = sources.OpenCVSource(
                    p.path if p.source == "video" else p.device,
                    v4l2=p.source == "v4l2",
                    width=p.width,
                    height=p.height,
                    fps=p.fps,
                    calibration=p.calibration,
                    hfov_deg=p.hfov_deg,
                )
            elif p.source == "rig":
                from stg_node.nodes.rig_sources import RigSource

                targets = [t.strip() for t in (p.devices or p.videos).split(",") if t.strip()]
                self.source = RigSource(p.rig, targets, v4l2=bool(p.devices), fps=p.fps, loop=p.loop)
            else:
                self.source = sources.OakSource(
                    replay=p.path,
                    width=p.width or 640,
                    height=p.height or 400,
                    fps=p.fps or 30.0,
                    calibration=p.calibration,
                )
        except (SourceError, ValueError, OSError) as exc:  # DatasetError is a ValueError
            raise SourceError(f"ingest cannot open its {p.source} source: {exc}") from exc
        self.pace = self.subscribe(p.pace_topic) if p.rate_hz == 0 else None
        self.acked_seq = -1
        self.published = 0
        self.rig_dropped = 0

    def _rate(self) -> float:
        if self.params.rate_hz > 0:
            return self.params.rate_hz
        if self.params.rate_hz < 0 and not getattr(self.source, "live", False):
            return float(self.source.fps or 30.0)
        return 0.0  # live sources deliver at their own rate; 0 = paced by acknowledgements

    def _wait_for_ack(self, seq: int) -> None:
        deadline = time.monotonic() + self.params.pace_timeout_s
        while self.acked_seq < seq - 1 - self.params.max_ahead and not self.stopping:
            msg = self.pace.recv(timeout=min(0.1, max(0.0, deadline - time.monotonic())))
            if msg is not None:
                self.acked_seq = max(self.acked_seq, int(getattr(msg, "frame_seq", -1)))
            elif time.monotonic() >= deadline:
                return

    def _publish(self, captured: CapturedFrame) -> None:
        cam = captured.camera
        frame = Frame(
            index=int(captured.index),
            time=float(captured.time),
            camera_id=cam.name,
            image=captured.image,
            mask=captured.mask,
            K=cam.K,
            R=cam.R,
            t=cam.t,
        )
        topic = None
        if self.params.source == "rig":
            from stg_node.nodes.rig import camera_topic

            topic = camera_topic(self.topic("camera/frame"), cam.name)
            dropped = sum(self.source.dropped().values())
            if dropped > self.rig_dropped:  # frames a camera delivered faster than we published
                self.drop("camera_backlog", dropped - self.rig_dropped)
                self.rig_dropped = dropped
        self.publish(frame, topic=topic, stamp_ns=captured.stamp_ns or None)
        self.published += 1

    def run(self) -> None:
        p = self.params
        watched = self.topic("camera/frame")
        if p.source == "rig":
            from stg_node.nodes.rig import camera_topic

            watched = camera_topic(watched, self.source.names[0])
        if p.wait_subscribers_s > 0 and not self.bus.publisher.wait_for_subscribers(
            watched, timeout=p.wait_subscribers_s
        ):
            self.log.info("nobody subscribes to camera/frame yet; publishing anyway")
        rate = self._rate()
        period = 1.0 / rate if rate > 0 else 0.0
        next_time = time.monotonic()
        passes = 0
        while not self.stopping:
            for captured in self.source.frames():
                if self.stopping:
                    break
                if self.pace is not None:
                    while (msg := self.pace.recv(timeout=0)) is not None:
                        self.acked_seq = max(self.acked_seq, int(getattr(msg, "frame_seq", -1)))
                    self._wait_for_ack(self.published)
                elif period:
                    delay = next_time - time.monotonic()
                    if delay > 0 and not self.sleep(delay):
                        break
                    next_time = max(next_time + period, time.monotonic() - period)  # no catch-up burst
                self._publish(captured)
                if p.max_frames and self.published >= p.max_frames:
                    self.log.info("published %d frames (max_frames)", self.published)
                    return
            passes += 1
            if not p.loop or p.source in ("v4l2", "oak", "rig"):  # a rig loops its own files
                break
            if p.source == "video":  # a fresh capture for the next pass
                self.setup_source_again()
        if not self.stopping:
            self.log.info("end of the source after %d frames", self.published)

    def setup_source_again(self) -> None:
        from stg_node.nodes import sources

        p = self.params
        self.source = sources.OpenCVSource(
            p.path,
            v4l2=False,
            width=p.width,
            height=p.height,
            fps=p.fps,
            calibration=p.calibration,
            hfov_deg=p.hfov_deg,
        )
