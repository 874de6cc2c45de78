"""Images out of a recording: an MP4 (or AVI) through OpenCV's VideoWriter, or a folder of PNGs.

    export_images(BagReader("session.mcap"), "avatar/image", "out.mp4")     # or "frames/" for PNGs

Any message with an ``image`` array (H, W, 3) uint8 RGB (Frame, RenderedImage) can be
exported; ``array`` picks another one (``mask``, ``alpha``: H x W uint8). A video takes
its size from the first image (later images of another size are resized, and counted) and
its frame rate from the recording (messages over duration) unless ``fps`` is given.
OpenCV is imported here only, on use: the bus package itself stays light.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stg_node.bus.recording.format import RecordingError
from stg_node.bus.recording.reader import BagReader
from stg_node.bus.stats import per_second
from stg_node.progress import progress

log = logging.getLogger(__name__)

VIDEO_CODECS = {".mp4": "mp4v", ".avi": "MJPG", ".mkv": "mp4v"}


@dataclass
class ExportStats:
    images: int = 0
    resized: int = 0
    skipped: int = 0  # messages on the topic without the array
    fps: float = 0.0
    out: str = ""


def _topic_rate(reader: BagReader, topic: str) -> float:
    """Messages per second on ``topic`` over its own span (30 when it cannot tell)."""
    count = sum(f.topic_messages.get(topic, 0) for f in reader.files)
    spans = [f.topic_times[topic] for f in reader.files if f.topic_times and topic in f.topic_times]
    if spans:
        start, end = min(s[0] for s in spans), max(s[1] for s in spans)
    else:
        start, end = reader.start_ns, reader.end_ns
    if count < 2 or start is None or end is None or end <= start:
        return 30.0
    return per_second(count - 1, (end - start) / 1e9)


def _as_bgr(arr: np.ndarray, cv2) -> np.ndarray:
    if arr.dtype != np.uint8:
        raise RecordingError(f"array of dtype {arr.dtype} is not an 8-bit image")
    if arr.ndim == 2:
        return cv2.cvtColor(np.ascontiguousarray(arr), cv2.COLOR_GRAY2BGR)
    if arr.ndim == 3 and arr.shape[2] == 3:
        return cv2.cvtColor(np.ascontiguousarray(arr), cv2.COLOR_RGB2BGR)
    raise RecordingError(f"array of shape {list(arr.shape)} is not an H x W or H x W x 3 image")


def export_images(
    reader: BagReader,
    topic: str,
    out: str | Path,
    *,
    array: str = "image",
    fps: float | None = None,
    png: bool | None = None,
    show_progress: bool = True,
) -> ExportStats:
    """Write the ``array`` of every message on ``topic`` to a video file or a PNG folder.

    ``png``: None decides by ``out`` (a known video suffix: video; else a folder of PNGs).
    """
    import cv2  # noqa: PLC0415 (heavy; only exports need it)

    out = Path(out)
    types = reader.types()
    if topic not in types:
        known = ", ".join(sorted(types)) or "none"
        files = ", ".join(str(f.path) for f in reader.files)
        damage = "; ".join(f"{f.path.name} is damaged: {f.problem}" for f in reader.files if f.problem)
        raise RecordingError(
            f"{files}: topic {topic!r} is not in the recording (topics: {known})"
            + (f"; {damage}" if damage else "")
        )
    if png is None:
        png = out.suffix.lower() not in VIDEO_CODECS
    if not png and out.suffix.lower() not in VIDEO_CODECS:
        raise RecordingError(f"{out}: video suffix must be one of {sorted(VIDEO_CODECS)}")
    stats = ExportStats(fps=fps or _topic_rate(reader, topic), out=str(out))
    total = sum(f.topic_messages.get(topic, 0) for f in reader.files)
    video = None
    size = None
    if png:
        out.mkdir(parents=True, exist_ok=True)
    else:
        out.parent.mkdir(parents=True, exist_ok=True)
    try:
        bar = progress(total=total, desc=f"export {topic}", unit="img", enabled=show_progress)
        with bar:
            for msg in reader.messages([f"^{re.escape(topic)}$"]):
                bar.update(1)
                env = msg.envelope()
                arr = env.arrays.get(array)
                if arr is None:
                    stats.skipped += 1
                    continue
                bgr = _as_bgr(arr, cv2)
                if png:
                    path = out / f"{stats.images:06d}.png"
                    if not cv2.imwrite(str(path), bgr):
                        raise RecordingError(f"OpenCV could not write {path}")
                else:
                    if video is None:
                        size = (bgr.shape[1], bgr.shape[0])
                        fourcc = cv2.VideoWriter_fourcc(*VIDEO_CODECS[out.suffix.lower()])
                        video = cv2.VideoWriter(str(out), fourcc, stats.fps, size)
                        if not video.isOpened():
                            raise RecordingError(f"OpenCV cannot write a video to {out}")
                    if (bgr.shape[1], bgr.shape[0]) != size:
                        bgr = cv2.resize(bgr, size, interpolation=cv2.INTER_AREA)
                        stats.resized += 1
                    video.write(bgr)
                stats.images += 1
    finally:
        if video is not None:
            video.release()
    if stats.images == 0:
        raise RecordingError(f"no message on {topic!r} has an array {array!r}")
    if stats.resized:
        log.warning("%d image(s) of another size were resized to %s", stats.resized, size)
    return stats
