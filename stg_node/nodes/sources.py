"""Where the ingest node's images come from: a dataset, OpenCV (video file or V4L2), or an OAK camera.

Every source yields :class:`CapturedFrame` items (RGB image, optional mask, calibration, index,
time). OpenCV video files and V4L2 devices share one reader (:class:`OpenCVSource`): only the
open call differs, so testing with a video file tests the V4L2 path's reading, conversion and
end-of-stream handling. :class:`OakSource` builds a depthai v3 pipeline: a ``Camera`` node on a
device, or depthai's host-side ``ReplayVideo`` node for a video file (no device needed); both
feed the same output-queue reader.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stg_node.data.types import Camera
from stg_node.nodes.runtime import NodeError

log = logging.getLogger(__name__)


class SourceError(NodeError):
    """A source cannot be opened or read; says which and why."""


@dataclass
class CapturedFrame:
    index: int
    time: float  # seconds since the first frame
    image: np.ndarray  # (H, W, 3) uint8 RGB
    camera: Camera
    mask: np.ndarray | None = None
    stamp_ns: int = 0  # capture time (live sources), 0 = publish time


@dataclass(frozen=True)
class Calibration:
    """Intrinsics (and optionally extrinsics) of a live camera, scaled to the delivered size."""

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray

    @classmethod
    def from_file(cls, path: str | Path) -> Calibration:
        """JSON ``{"K": 3x3, "R": 3x3 (optional), "t": 3 (optional), "width": W, "height": H}``."""
        path = Path(path)
        try:
            data = json.loads(path.read_text())
            K = np.asarray(data["K"], np.float64).reshape(3, 3)
            R = np.asarray(data.get("R", np.eye(3)), np.float64).reshape(3, 3)
            t = np.asarray(data.get("t", np.zeros(3)), np.float64).reshape(3)
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
            raise SourceError(f"{path}: not a calibration file (JSON with K, optional R, t): {exc}") from exc
        problem = calibration_problem(K, R, t)
        if problem:
            raise SourceError(f"{path}: {problem}")
        return cls(K, R, t)

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float) -> Calibration:
        """A pinhole guess: principal point at the centre, focal length from the horizontal field of view."""
        f = 0.5 * width / math.tan(math.radians(hfov_deg) / 2)
        K = np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
        return cls(K, np.eye(3), np.zeros(3))

    def camera(self, width: int, height: int, name: str = "") -> Camera:
        return Camera(K=self.K, R=self.R, t=self.t, width=width, height=height, name=name)


def calibration_problem(K: np.ndarray, R: np.ndarray, t: np.ndarray) -> str:
    """What is wrong with a pinhole calibration (empty: nothing): every frame carries it, and a
    NaN or a mirrored camera would only show up later as a broken avatar."""
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        return "K, R and t must be finite numbers"
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
        return "K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0"
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        return "R must be a rotation (orthonormal, determinant +1)"
    return ""


def parse_frame_range(text: str):
    """'START:STOP[:STEP]' (STOP may be empty: to the end) -> stg_node.data.splits.FrameRange."""
    from stg_node.data.splits import FrameRange

    parts = text.split(":")
    try:
        if len(parts) not in (2, 3):
            raise ValueError
        start = int(parts[0] or 0)
        stop = int(parts[1]) if parts[1] else None
        step = int(parts[2]) if len(parts) == 3 and parts[2] else 1
    except ValueError:
        raise SourceError(f"train_frames {text!r} must look like START:STOP or START:STOP:STEP") from None
    if start < 0 or step < 1 or (stop is not None and stop <= start):
        raise SourceError(f"train_frames {text!r}: need 0 <= START < STOP and STEP >= 1")
    return FrameRange(start, stop, step)


# --- datasets ------------------------------------------------------------------------------------


class DatasetSource:
    """The views of one split of a dataset, in order (stg_node.data.open_dataset)."""

    def __init__(
        self,
        path: str,
        *,
        kind: str = "auto",
        split: str = "train",
        size: int | None = 512,
        camera: str = "",
        train_frames: str = "",
    ):
        from stg_node.data import open_dataset

        root = Path(path)
        options = {}
        if train_frames:
            options["train_frames"] = parse_frame_range(train_frames)
        if (root / "synth.json").is_file() and kind in ("auto", "synth"):
            from stg_node.data.synth.dataset import open_synth

            self.dataset = open_synth(root, split, size=size)
        else:
            self.dataset = open_dataset(
                root, "auto" if kind == "synth" else kind, split, size=size, **options
            )
        self.camera_name = camera
        self.views = [v for v in self.dataset.views if not camera or v.camera == camera]
        if not self.views:
            raise SourceError(f"{root}: split {split!r} has no view from camera {camera!r}")
        self.fps = self.dataset.fps

    def __len__(self) -> int:
        return len(self.views)

    def frames(self) -> Iterator[CapturedFrame]:
        for ref in self.views:
            sample = self.dataset.load(ref.frame, ref.camera)
            yield CapturedFrame(sample.index, sample.time, sample.image, sample.camera, sample.mask)


# --- OpenCV: video files and V4L2 ------------------------------------------------------------------


class OpenCVSource:
    """Frames from ``cv2.VideoCapture``: a video file, or a V4L2 device (index or /dev/videoN)."""

    def __init__(
        self,
        target: str,
        *,
        v4l2: bool,
        width: int = 0,
        height: int = 0,
        fps: float = 0.0,
        calibration: str = "",
        hfov_deg: float = 60.0,
        name: str = "",
    ):
        import cv2

        self._cv2 = cv2
        self.target = target
        if v4l2:
            device = int(target) if target.isdigit() else target
            self.capture = cv2.VideoCapture(device, cv2.CAP_V4L2)
            if width and height:
                self.capture.set(cv2.CAP_PROP_FRAME_WIDTH, width)
                self.capture.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
            if fps:
                self.capture.set(cv2.CAP_PROP_FPS, fps)
        else:
            if not Path(target).is_file():
                raise SourceError(f"video file {target!r} does not exist")
            self.capture = cv2.VideoCapture(target)
        if not self.capture.isOpened():
            what = "V4L2 device" if v4l2 else "video file"
            raise SourceError(f"cannot open {what} {target!r} with OpenCV")
        self.fps = float(self.capture.get(cv2.CAP_PROP_FPS) or 0.0) or (fps or 30.0)
        self.live = v4l2
        self.resize = (width, height) if (width and height and not v4l2) else None
        self.calibration_file = calibration
        self.hfov_deg = hfov_deg
        self.name = name or ("v4l2" if v4l2 else Path(target).stem)

    def frames(self) -> Iterator[CapturedFrame]:
        cv2 = self._cv2
        calibration = None
        index = 0
        first = None
        try:
            while True:
                ok, bgr = self.capture.read()
                stamp = time.time_ns()
                if not ok or bgr is None:
                    if self.live:
                        raise SourceError(f"V4L2 device {self.target!r} stopped delivering frames")
                    return  # end of the file
                if self.resize is not None:
                    bgr = cv2.resize(bgr, self.resize, interpolation=cv2.INTER_AREA)
                rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
                h, w = rgb.shape[:2]
                if calibration is None:
                    calibration = (
                        Calibration.from_file(self.calibration_file)
                        if self.calibration_file
                        else Calibration.from_fov(w, h, self.hfov_deg)
                    )
                if self.live:
                    first = first or stamp
                    t = (stamp - first) / 1e9
                else:
                    t = index / self.fps
                yield CapturedFrame(
                    index, t, rgb, calibration.camera(w, h, self.name), None, stamp if self.live else 0
                )
                index += 1
        finally:
            self.capture.release()


# --- OAK (depthai v3) --------------------------------------------------------------------------------


class OakSource:
    """Frames from an OAK camera through depthai, or from a video file through depthai's host-side
    ReplayVideo node (``replay``: no device needed). The reader is the same for both."""

    def __init__(
        self,
        *,
        replay: str = "",
        width: int = 640,
        height: int = 400,
        fps: float = 30.0,
        calibration: str = "",
        hfov_deg: float = 69.0,
        name: str = "oak",
    ):
        try:
            import depthai as dai
        except ImportError as exc:  # pragma: no cover - depthai is a dependency
            raise SourceError(f"depthai is not installed: {exc}") from exc
        self._dai = dai
        self.name = name
        self.fps = fps
        self.live = not replay
        self.calibration = Calibration.from_file(calibration) if calibration else None
        self.hfov_deg = hfov_deg
        try:
            if replay:
                if not Path(replay).is_file():
                    raise SourceError(f"video file {replay!r} for the OAK replay does not exist")
                self.pipeline = dai.Pipeline(False)  # host only: no device
                node = self.pipeline.create(dai.node.ReplayVideo)
                node.setReplayVideoFile(Path(replay))
                node.setOutFrameType(dai.ImgFrame.Type.RGB888i)
                node.setLoop(False)
                if fps:
                    node.setFps(fps)
                if width and height:
                    node.setSize(width, height)
                output = node.out
            else:
                self.pipeline = dai.Pipeline()  # opens the first OAK device found
                cam = self.pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_A)
                output = cam.requestOutput((width, height), dai.ImgFrame.Type.RGB888i, fps=fps)
                if self.calibration is None:
                    device = self.pipeline.getDefaultDevice()
                    K = device.readCalibration().getCameraIntrinsics(
                        dai.CameraBoardSocket.CAM_A, width, height
                    )
                    self.calibration = Calibration(np.asarray(K, np.float64), np.eye(3), np.zeros(3))
            self.queue = output.createOutputQueue(maxSize=4, blocking=False)
        except SourceError:
            raise
        except Exception as exc:
            raise SourceError(
                f"cannot build the depthai pipeline ({'replay ' + replay if replay else 'device'}): {exc}"
            ) from exc

    def frames(self) -> Iterator[CapturedFrame]:
        dai = self._dai
        self.pipeline.start()
        index = 0
        first = None
        try:
            while self.pipeline.isRunning():
                try:
                    msg = self.queue.tryGet()
                except RuntimeError:  # the queue closes when a replay ends
                    break
                if msg is None:
                    time.sleep(0.002)
                    continue
                stamp = time.time_ns()
                frame = msg.getCvFrame()  # BGR, as OpenCV uses
                rgb = (
                    np.ascontiguousarray(frame[..., ::-1])
                    if frame.ndim == 3
                    else np.repeat(frame[..., None], 3, 2)
                )
                h, w = rgb.shape[:2]
                if self.calibration is None:
                    self.calibration = Calibration.from_fov(w, h, self.hfov_deg)
                first = first or stamp
                t = (stamp - first) / 1e9 if self.live else index / (self.fps or 30.0)
                yield CapturedFrame(
                    index, t, rgb, self.calibration.camera(w, h, self.name), None, stamp if self.live else 0
                )
                index += 1
        finally:
            try:
                self.pipeline.stop()
            except Exception:  # already stopped
                pass
            del dai
