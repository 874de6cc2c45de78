"""The rig ingest source: several cameras at once, each frame stamped at capture, undistorted.

:class:`RigSource` opens one OpenCV capture per camera of a rig (rig.json), V4L2 devices or
video files, in the rig's camera order, and reads each in its own thread, so a slow camera never
delays another and every frame's stamp is its own capture time:

- V4L2: the driver's buffer time stamp (``CAP_PROP_POS_MSEC``: the kernel's monotonic clock when
  the frame was captured, not when we read it) moved onto the wall clock; where the driver gives
  none, the time ``grab`` returned.
- video files (a rig without cameras, tests): each file played in real time from a common
  start, stamped with the start plus its presentation time, so files recorded together stay
  together.

Frames are undistorted with the camera's lens (rig.json ``dist``; the published ``K`` is then a
pinhole one) and carry the rig's world-to-camera ``R``, ``t``, so the tracker fits in the rig's
world frame. A reader keeps at most two frames its consumer has not taken (older ones are
dropped and counted): the ingest never lags its cameras.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import deque
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from stg_node.data.types import Camera
from stg_node.nodes.sources import CapturedFrame, SourceError

log = logging.getLogger(__name__)

BACKLOG = 2  # frames a camera may hold for its consumer before the oldest is dropped
PLAUSIBLE_CLOCK_S = 5.0  # a driver stamp further than this from now is not a capture time


def _monotonic_to_wall_ns(monotonic_ms: float) -> int:
    """A CLOCK_MONOTONIC time (ms, as V4L2 buffers carry) on the wall clock (ns)."""
    offset = time.time_ns() - time.monotonic_ns()
    return int(monotonic_ms * 1e6) + offset


class _Reader(threading.Thread):
    """Reads one camera into a short queue until told to stop."""

    def __init__(self, source: RigSource, slot: int, target: str, stop: threading.Event):
        super().__init__(name=f"rig-{source.names[slot]}", daemon=True)
        self.source = source
        self.slot = slot
        self.target = target
        self.stop_event = stop
        self.frames: deque = deque(maxlen=BACKLOG)
        self.dropped = 0
        self.error: Exception | None = None
        self.finished = False

    def run(self) -> None:
        try:
            self._read()
        except Exception as exc:  # handed to the consumer, which raises it
            self.error = exc
        finally:
            self.finished = True
            self.source._wake.put(self.slot)

    def _open(self):
        src = self.source
        if src.v4l2:
            device = int(self.target) if self.target.isdigit() else self.target
            capture = cv2.VideoCapture(device, cv2.CAP_V4L2)
            width, height = src.rig.cameras[self.slot].image_size
            capture.set(cv2.CAP_PROP_FRAME_WIDTH, width)
            capture.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
            if src.fps:
                capture.set(cv2.CAP_PROP_FPS, src.fps)
        else:
            if not Path(self.target).is_file():
                raise SourceError(
                    f"video file {self.target!r} for camera {src.names[self.slot]} does not exist"
                )
            capture = cv2.VideoCapture(self.target)
        if not capture.isOpened():
            what = "V4L2 device" if src.v4l2 else "video file"
            raise SourceError(f"cannot open {what} {self.target!r} for camera {src.names[self.slot]}")
        return capture

    def _read(self) -> None:
        src = self.source
        name = src.names[self.slot]
        passes = 0
        while not self.stop_event.is_set():
            capture = self._open()
            fps = float(capture.get(cv2.CAP_PROP_FPS) or 0.0) or (src.fps or 30.0)
            start_ns = src.start_ns + int(passes * src.pass_s * 1e9) if not src.v4l2 else 0
            index = 0
            try:
                while not self.stop_event.is_set():
                    if not src.v4l2:  # play the file in real time from the common start
                        due = start_ns + int(index / fps * 1e9)
                        delay = (due - time.time_ns()) / 1e9
                        if delay > 0 and self.stop_event.wait(delay):
                            return
                    if not capture.grab():
                        if src.v4l2:
                            raise SourceError(
                                f"V4L2 device {self.target!r} (camera {name}) stopped delivering frames"
                            )
                        break
                    grabbed_ns = time.time_ns()
                    ok, bgr = capture.retrieve()
                    if not ok or bgr is None:
                        continue
                    if src.v4l2:
                        stamp_ns = grabbed_ns
                        msec = capture.get(cv2.CAP_PROP_POS_MSEC)
                        if msec and msec > 0:
                            driver_ns = _monotonic_to_wall_ns(msec)
                            if abs(driver_ns - grabbed_ns) < PLAUSIBLE_CLOCK_S * 1e9:
                                stamp_ns = driver_ns
                    else:
                        stamp_ns = start_ns + int(index / fps * 1e9)
                    image = src.prepare(self.slot, bgr)
                    if len(self.frames) == self.frames.maxlen:
                        self.dropped += 1
                    self.frames.append((stamp_ns, index, image))
                    src._wake.put(self.slot)
                    index += 1
            finally:
                capture.release()
            passes += 1
            if src.v4l2 or not src.loop:
                return


class RigSource:
    """The cameras of a rig, read at once (see the module docstring); ``frames()`` yields
    :class:`CapturedFrame` items of every camera as they come, ``.camera.name`` naming the camera."""

    live = True  # paced by its cameras (or by the files' real-time playback)

    def __init__(
        self,
        rig_path: str,
        targets: list[str],
        *,
        v4l2: bool,
        cameras: list[str] | None = None,
        fps: float = 0.0,
        loop: bool = False,
    ):
        from stg_node.calibration.rig import RigError, read_rig

        try:
            rig = read_rig(rig_path)
            if cameras:
                rig = rig.select(cameras)
        except RigError as exc:
            raise SourceError(str(exc)) from exc
        if len(targets) != len(rig):
            raise SourceError(
                f"{len(targets)} {'devices' if v4l2 else 'videos'} for the rig's {len(rig)} cameras "
                f"({', '.join(rig.names)}): give one per camera, in that order"
            )
        self.rig = rig
        self.names = rig.names
        self.targets = list(targets)
        self.v4l2 = v4l2
        self.fps = fps
        self.loop = loop
        self._maps = [self._undistort_map(c) for c in rig.cameras]
        self._wake: queue.Queue = queue.Queue()
        self.start_ns = 0
        self.pass_s = 0.0
        if not v4l2:
            lengths = []
            for target in self.targets:
                capture = cv2.VideoCapture(target)
                count = capture.get(cv2.CAP_PROP_FRAME_COUNT) or 0
                rate = capture.get(cv2.CAP_PROP_FPS) or (fps or 30.0)
                capture.release()
                lengths.append(count / rate if count else 0.0)
            self.pass_s = max(lengths) + 1.0  # a looping replay starts every pass together

    @staticmethod
    def _undistort_map(camera):
        if not camera.dist.size or not np.any(camera.dist):
            return None
        return cv2.initUndistortRectifyMap(
            camera.K, camera.dist, None, camera.K, camera.image_size, cv2.CV_32FC1
        )

    def camera(self, slot: int) -> Camera:
        """The published camera of ``slot``: pinhole ``K`` (frames are undistorted), the rig's R, t."""
        c = self.rig.cameras[slot]
        return Camera(K=c.K, R=c.R, t=c.t, width=c.width, height=c.height, name=c.name)

    def prepare(self, slot: int, bgr: np.ndarray) -> np.ndarray:
        """A captured BGR frame as the published RGB one (checked size, undistorted)."""
        camera = self.rig.cameras[slot]
        if (bgr.shape[1], bgr.shape[0]) != camera.image_size:
            raise SourceError(
                f"camera {camera.name} delivers {bgr.shape[1]}x{bgr.shape[0]} frames, but the rig is "
                f"calibrated at {camera.width}x{camera.height} (ask the device for that size, or calibrate "
                "again)"
            )
        if self._maps[slot] is not None:
            bgr = cv2.remap(bgr, *self._maps[slot], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def dropped(self) -> dict[str, int]:
        return {self.names[r.slot]: r.dropped for r in getattr(self, "_readers", [])}

    def frames(self) -> Iterator[CapturedFrame]:
        stop = threading.Event()
        self.start_ns = time.time_ns() + 200_000_000  # every reader opens its file before the start
        readers = [_Reader(self, slot, target, stop) for slot, target in enumerate(self.targets)]
        self._readers = readers
        first_ns = None
        for reader in readers:
            reader.start()
        try:
            while True:
                try:
                    self._wake.get(timeout=0.5)
                except queue.Empty:
                    pass
                for reader in readers:
                    if reader.error is not None:
                        raise reader.error
                pending = [(r.frames[0][0], r) for r in readers if r.frames]
                if not pending:
                    if all(r.finished for r in readers):
                        return
                    continue
                for stamp_ns, reader in sorted(pending, key=lambda p: p[0]):
                    _, index, image = reader.frames.popleft()
                    first_ns = stamp_ns if first_ns is None else first_ns
                    yield CapturedFrame(
                        index, (stamp_ns - first_ns) / 1e9, image, self.camera(reader.slot), None, stamp_ns
                    )
        finally:
            stop.set()
            for reader in readers:
                reader.join(timeout=5.0)
            still = [r.name for r in readers if r.is_alive()]
            if still:
                log.warning("camera readers %s did not stop within 5 s", still)
