"""Frames of several cameras matched by time stamp: what a rig's calibration and tracking read.

A rig records one video (or image folder) per camera. Each file has its own clock, starting at
its first frame: the container's presentation times for videos, ``index / fps`` for folders
(tracking/sources.py), or, when a file ``STEM.timestamps.txt`` lies beside the video, the
capture times it lists (mkvmerge's "timestamp format v2": one time in milliseconds per line, the
first line may be ``# timestamp format v2``; ``ffmpeg -i CAM.mp4 -f mkvtimestamp_v2
CAM.timestamps.txt`` writes one), which is how frames dropped during recording stay in their
place. :func:`match_frames` pairs them by those times: the camera with the
lowest frame rate leads (a 60 fps camera beside a 30 fps one gives every other frame), and for
each of its frames every other camera contributes its frame nearest in time. When that nearest
frame is further away than ``max_skew_s`` (default: half the leading camera's frame period) the
inputs are not synchronised: :class:`UnsynchronisedError` says which camera, by how much, where,
and how fast the gap grows (a 29.97 fps camera beside a 30 fps one drifts by 1 ms every second).
Nothing is decoded twice: time stamps are read first (``grab`` without decoding), the match is
checked before any work starts, then :func:`synced_frames` decodes each file once, in step.

:class:`StampMatcher` does the same for live frames arriving one by one (the tracker node):
the newest complete set whose stamps lie within the tolerance of each other.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from stg_node.tracking.sources import ImageFolderSource, SourceFrame, VideoSource, open_source

log = logging.getLogger(__name__)


class UnsynchronisedError(ValueError):
    """The cameras' frames cannot be paired in time; the message says by how much they drift."""


@dataclass(frozen=True)
class FrameMatch:
    """Which frame of each camera belongs to each matched instant."""

    names: tuple[str, ...]  # camera names, in input order
    indices: np.ndarray  # (N, V) int frame index of each camera at each instant
    times: np.ndarray  # (N,) seconds: the leading camera's time stamps
    skew: np.ndarray  # (N, V) seconds: each camera's time minus the leading camera's
    leader: int  # the camera whose frames set the instants
    dropped: dict[str, int]  # frames of each camera no instant used

    def __len__(self) -> int:
        return int(self.indices.shape[0])

    @property
    def max_skew_s(self) -> float:
        return float(np.abs(self.skew).max()) if self.skew.size else 0.0


def sidecar_path(video: str | Path) -> Path:
    """Where a video's capture times may lie: ``STEM.timestamps.txt`` beside it."""
    video = Path(video)
    return video.with_name(video.stem + ".timestamps.txt")


def read_sidecar(path: str | Path) -> np.ndarray:
    """(N,) seconds from a "timestamp format v2" file (milliseconds per line; # comments)."""
    path = Path(path)
    values = []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        try:
            values.append(float(line) / 1000.0)
        except ValueError:
            raise UnsynchronisedError(f"{path}:{number}: {line!r} is not a time in milliseconds") from None
    if not values:
        raise UnsynchronisedError(f"{path}: lists no time stamps")
    return np.asarray(values, dtype=np.float64)


def read_timestamps(source) -> np.ndarray:
    """(N,) seconds of every frame of a video (its ``STEM.timestamps.txt`` if there is one, else
    the container's, read by ``grab`` without decoding) or image folder."""
    if isinstance(source, ImageFolderSource):
        return np.arange(len(source), dtype=np.float64) / source.fps
    if not isinstance(source, VideoSource):
        raise TypeError(f"cannot read time stamps of {type(source).__name__}")
    sidecar = sidecar_path(source.path)
    if sidecar.is_file():
        return read_sidecar(sidecar)
    capture = cv2.VideoCapture(str(source.path))
    stamps: list[float] = []
    try:
        previous = -1.0
        while capture.grab():
            index = len(stamps)
            stamp = index / source.fps
            if source._use_stream_time:  # the same rule as VideoSource.__iter__
                msec = capture.get(cv2.CAP_PROP_POS_MSEC)
                if msec and msec / 1000.0 > previous:
                    stamp = msec / 1000.0
            previous = stamp
            stamps.append(stamp)
    finally:
        capture.release()
    if not stamps:
        raise UnsynchronisedError(f"{source.path}: no frame could be read")
    return np.asarray(stamps, dtype=np.float64)


def _frame_rate(times: np.ndarray) -> float:
    """The nominal rate: from the median frame interval (a stall does not lower it)."""
    if len(times) < 2:
        return float("nan")
    return float(1.0 / max(np.median(np.diff(times)), 1e-9))


def match_frames(
    times: Sequence[np.ndarray], names: Sequence[str], max_skew_s: float | None = None
) -> FrameMatch:
    """Pair the cameras' frames by time stamp (see the module docstring); raise when they drift apart.

    ``times``: each camera's frame times in seconds (increasing). ``max_skew_s``: the largest
    allowed distance to the leading camera's frame (None: half its frame period).
    """
    if len(times) != len(names) or not names:
        raise ValueError(f"need one time list per camera, got {len(times)} lists for {len(names)} names")
    times = [np.asarray(t, dtype=np.float64).reshape(-1) for t in times]
    for name, t in zip(names, times, strict=True):
        if t.size == 0:
            raise UnsynchronisedError(f"camera {name!r} has no frames")
        if np.any(np.diff(t) <= 0):
            raise UnsynchronisedError(f"camera {name!r}: frame times do not increase")
    rates = [_frame_rate(t) for t in times]
    finite = [round(r, 3) if np.isfinite(r) else np.inf for r in rates]
    leader = int(np.argmin(finite))  # the slowest; ties: the first
    lead = times[leader]
    period = 1.0 / rates[leader] if np.isfinite(rates[leader]) else 1.0 / 30.0
    tolerance = 0.5 * period if max_skew_s is None else float(max_skew_s)
    # Instants: the leader's frames that every camera covers (no camera ended or not yet begun).
    start = max(t[0] for t in times) - tolerance
    stop = min(t[-1] for t in times) + tolerance
    keep = (lead >= start) & (lead <= stop)
    if not keep.any():
        spans = ", ".join(f"{n} {t[0]:.2f}-{t[-1]:.2f} s" for n, t in zip(names, times, strict=True))
        raise UnsynchronisedError(f"the cameras' recordings do not overlap in time ({spans})")
    instants = lead[keep]
    indices = np.zeros((len(instants), len(names)), dtype=np.int64)
    skew = np.zeros((len(instants), len(names)))
    for v, t in enumerate(times):
        right = np.clip(np.searchsorted(t, instants), 0, len(t) - 1)
        left = np.clip(right - 1, 0, len(t) - 1)
        nearest = np.where(np.abs(t[left] - instants) <= np.abs(t[right] - instants), left, right)
        indices[:, v] = nearest
        skew[:, v] = t[nearest] - instants
    worst = np.abs(skew)
    if worst.max() > tolerance:
        row, v = np.unravel_index(int(np.argmax(worst > tolerance)), worst.shape)
        slope = np.polyfit(instants, skew[:, v], 1)[0] if len(instants) > 1 else 0.0
        late = worst[:, v] > tolerance
        raise UnsynchronisedError(
            f"camera {names[v]!r} is not synchronised with {names[leader]!r}: its nearest frame is "
            f"{1e3 * skew[row, v]:+.1f} ms away at {instants[row]:.2f} s "
            f"(tolerance {1e3 * tolerance:.1f} ms), "
            f"{1e3 * worst[:, v].max():.1f} ms at worst, at {int(late.sum())} of {len(instants)} instants; "
            f"the gap drifts by {1e3 * slope:+.2f} ms per second ({rates[v]:.3f} fps against "
            f"{rates[leader]:.3f}). Record the cameras with one clock (launch/rig_v4l2.yaml stamps frames "
            "at capture), give each video its capture times (STEM.timestamps.txt), or trim the videos to a "
            "common start (a clap in view)"
        )
    dropped = {}
    for v, name in enumerate(names):
        unused = len(times[v]) - len(np.unique(indices[:, v]))
        if unused:
            dropped[name] = int(unused)
    return FrameMatch(tuple(names), indices, instants, skew, leader, dropped)


@dataclass(frozen=True)
class FrameSet:
    """One instant of the rig: a frame from every camera."""

    index: int  # position in the match (0, 1, ...)
    time: float  # seconds (the leading camera's time stamp)
    frames: tuple[SourceFrame, ...]  # in camera order


def open_sources(paths: Sequence[str | Path], fps: float | None = None) -> list:
    return [open_source(p, fps) for p in paths]


def match_sources(sources: Sequence, names: Sequence[str], max_skew_s: float | None = None) -> FrameMatch:
    """Read every source's time stamps and match them (:func:`match_frames`)."""
    match = match_frames([read_timestamps(s) for s in sources], names, max_skew_s)
    for name, count in match.dropped.items():
        log.info("camera %s: %d frames have no partner in time and are skipped", name, count)
    return match


def synced_frames(sources: Sequence, match: FrameMatch, every: int = 1) -> Iterator[FrameSet]:
    """Decode each source once, in step, yielding the matched sets (every ``every``-th instant)."""
    iterators = [iter(s) for s in sources]
    current: list[SourceFrame | None] = [None] * len(sources)
    try:
        for row in range(0, len(match), max(1, every)):
            frames = []
            for v, it in enumerate(iterators):
                wanted = int(match.indices[row, v])
                while current[v] is None or current[v].index < wanted:
                    try:
                        current[v] = next(it)
                    except StopIteration:
                        raise UnsynchronisedError(
                            f"camera {match.names[v]!r} ended at frame "
                            f"{current[v].index if current[v] else -1}, before frame {wanted} its time "
                            "stamps promised"
                        ) from None
                frames.append(current[v])
            yield FrameSet(row, float(match.times[row]), tuple(frames))
    finally:
        for it in iterators:
            close = getattr(it, "close", None)
            if close is not None:
                close()


class StampMatcher:
    """Live frames of several cameras in, complete sets out (the newest whose stamps agree).

    ``push(camera, stamp_ns, item)`` keeps the last ``depth`` frames of each camera; it returns
    the newest set with one frame per camera within ``tolerance_ns`` of the newest one's stamp
    whenever one exists that is newer than the last set returned (else None). Older frames of a
    set's cameras are forgotten, so a set is never returned twice.
    """

    def __init__(self, cameras: Sequence[str], tolerance_ns: int, depth: int = 8):
        if not cameras:
            raise ValueError("StampMatcher needs at least one camera")
        if tolerance_ns < 0:
            raise ValueError(f"tolerance_ns must be >= 0, got {tolerance_ns}")
        self.cameras = tuple(cameras)
        self.tolerance_ns = int(tolerance_ns)
        self._buffers: dict[str, deque] = {c: deque(maxlen=max(1, depth)) for c in self.cameras}
        self.incomplete = 0  # frames forgotten without joining a set

    def push(self, camera: str, stamp_ns: int, item) -> tuple[int, dict] | None:
        """Add one frame; ``(stamp_ns, {camera: item})`` of a new complete set, or None."""
        if camera not in self._buffers:
            raise KeyError(f"camera {camera!r} is not one of {self.cameras}")
        buffer = self._buffers[camera]
        if buffer and stamp_ns <= buffer[-1][0]:
            buffer.clear()  # a clock that went back (a restarted camera): start this camera afresh
        if len(buffer) == buffer.maxlen:
            self.incomplete += 1
        buffer.append((int(stamp_ns), item))
        return self._complete()

    def _complete(self) -> tuple[int, dict] | None:
        if any(not b for b in self._buffers.values()):
            return None
        # Every buffered frame is newer than the last set's (those were forgotten), so any
        # complete set is new: try reference stamps newest first.
        candidates = sorted({s for b in self._buffers.values() for s, _ in b}, reverse=True)
        for reference in candidates:
            chosen = {}
            for camera, buffer in self._buffers.items():
                best = min(buffer, key=lambda entry: abs(entry[0] - reference))
                if abs(best[0] - reference) > self.tolerance_ns:
                    break
                chosen[camera] = best
            else:
                for camera, (used, _) in chosen.items():
                    buffer = self._buffers[camera]
                    while buffer and buffer[0][0] <= used:
                        buffer.popleft()
                stamp = max(s for s, _ in chosen.values())
                return stamp, {camera: item for camera, (_, item) in chosen.items()}
        return None
