"""Frames to track: a video file (anything OpenCV's FFmpeg backend decodes) or a folder of images.

:func:`open_source` picks by what the path is. Each frame comes with its index and a time stamp
in seconds: the container's presentation time for videos (falling back to index / fps), index /
fps for folders (``fps`` given, default 30). Images in a folder are taken in natural order of
their names (``frame2`` before ``frame10``); files that are not images are skipped, unreadable
images raise with the file named.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from stg_node.data.io import IMAGE_SUFFIXES, read_image

DEFAULT_FPS = 30.0


class SourceError(ValueError):
    """The input cannot be read as frames; the message names the path."""


@dataclass(frozen=True)
class SourceFrame:
    index: int
    timestamp: float  # seconds
    image: np.ndarray  # (H, W, 3) uint8 RGB


def _natural_key(path: Path):
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", path.name)]


class ImageFolderSource:
    """The images of one folder, in natural name order, at a fixed frame rate."""

    def __init__(self, folder: str | Path, fps: float | None = None):
        self.path = Path(folder)
        self.files = sorted(
            (p for p in self.path.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
            key=_natural_key,
        )
        if not self.files:
            raise SourceError(f"{self.path}: no images ({', '.join(IMAGE_SUFFIXES)}) in this folder")
        self.fps = float(fps or DEFAULT_FPS)
        if not self.fps > 0:
            raise SourceError(f"fps must be positive, got {self.fps}")
        first = read_image(self.files[0])
        self.height, self.width = first.shape[:2]

    def __len__(self) -> int:
        return len(self.files)

    def __iter__(self) -> Iterator[SourceFrame]:
        for index, path in enumerate(self.files):
            image = read_image(path)
            if image.shape[:2] != (self.height, self.width):
                raise SourceError(
                    f"{path}: {image.shape[1]}x{image.shape[0]} pixels, but the folder's first image is "
                    f"{self.width}x{self.height} (one camera, one size)"
                )
            yield SourceFrame(index, index / self.fps, image)


class VideoSource:
    """A video file decoded with OpenCV; frames as RGB."""

    def __init__(self, path: str | Path, fps: float | None = None):
        self.path = Path(path)
        if not self.path.is_file():
            raise SourceError(f"{self.path}: no such video file")
        capture = cv2.VideoCapture(str(self.path))
        try:
            if not capture.isOpened():
                raise SourceError(f"{self.path}: OpenCV cannot open it as a video")
            self.width = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH))
            self.height = int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
            native = float(capture.get(cv2.CAP_PROP_FPS) or 0.0)
            self._count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        finally:
            capture.release()
        if self.width <= 0 or self.height <= 0:
            raise SourceError(f"{self.path}: the video reports no frame size (corrupt or empty?)")
        self.fps = float(fps or (native if 0 < native < 1000 else DEFAULT_FPS))
        self._use_stream_time = fps is None

    def __len__(self) -> int:
        """Frame count from the container (may be approximate; 0 when unknown)."""
        return max(self._count, 0)

    def __iter__(self) -> Iterator[SourceFrame]:
        capture = cv2.VideoCapture(str(self.path))
        try:
            if not capture.isOpened():
                raise SourceError(f"{self.path}: OpenCV cannot open it as a video")
            index = 0
            previous = -1.0
            while True:
                ok, bgr = capture.read()
                if not ok or bgr is None:
                    break
                stamp = index / self.fps
                if self._use_stream_time:
                    msec = capture.get(cv2.CAP_PROP_POS_MSEC)
                    # Some containers report 0 or non-increasing times: fall back to index / fps.
                    if msec and msec / 1000.0 > previous:
                        stamp = msec / 1000.0
                previous = stamp
                yield SourceFrame(index, stamp, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
                index += 1
            if index == 0:
                raise SourceError(f"{self.path}: no frame could be decoded")
        finally:
            capture.release()


def open_source(path: str | Path, fps: float | None = None) -> ImageFolderSource | VideoSource:
    """A frame source for a video file or an image folder."""
    path = Path(path)
    if path.is_dir():
        return ImageFolderSource(path, fps)
    if path.is_file():
        return VideoSource(path, fps)
    raise SourceError(f"{path}: neither a video file nor a folder of images")
