"""Training frames and the bounded store the trainer samples from.

A :class:`TrainFrame` is one image of the person with its camera, SMPL parameters and time (the
same fields as a dataset's FrameSample, or a bus Frame + BodyPose pair). The store keeps what a
step needs ready: the crop window around the person (the trainer renders only that), the
masked image, and the optical flow to the frame that followed it in the same camera (frames of
several cameras may arrive interleaved: each camera's last frame is remembered), together
with that next frame's pose and time (so a frame keeps its flow even after its successor is
evicted). With ``capacity`` set the store is a reservoir sample of the stream (memory stays flat
on an endless stream, and old and new frames stay represented).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from stg_node.data.flow import FlowCache, FlowPair, FlowSettings, compute_flow_pair
from stg_node.data.types import Camera

log = logging.getLogger(__name__)


@dataclass
class TrainFrame:
    """One training view: the fields of a dataset FrameSample."""

    index: int  # frame number in the sequence (consecutive frames differ by 1)
    time: float  # seconds since the sequence started
    image: np.ndarray  # (H, W, 3) uint8 RGB
    mask: np.ndarray | None  # (H, W) uint8 0/255, or None
    camera: Camera
    smpl: object  # SmplParams: poses (24, 3), Rh (3,), Th (3,), betas (S,)

    @classmethod
    def from_sample(cls, sample) -> TrainFrame:
        return cls(sample.index, sample.time, sample.image, sample.mask, sample.camera, sample.smpl)

    def check(self) -> None:
        h, w = int(self.camera.height), int(self.camera.width)
        if self.image.shape != (h, w, 3) or self.image.dtype != np.uint8:
            raise ValueError(
                f"frame {self.index}: image must be ({h}, {w}, 3) uint8 like its camera, got "
                f"{self.image.shape} {self.image.dtype}"
            )
        if self.mask is not None and self.mask.shape != (h, w):
            raise ValueError(f"frame {self.index}: mask must be ({h}, {w}), got {self.mask.shape}")
        for name in ("poses", "Rh", "Th"):
            if not np.all(np.isfinite(getattr(self.smpl, name))):
                raise ValueError(f"frame {self.index}: SMPL {name} has NaN or infinite values")
        if not np.isfinite(self.time):
            raise ValueError(f"frame {self.index}: time {self.time} is not finite")


@dataclass
class StoredFrame:
    frame: TrainFrame
    crop: tuple[int, int, int, int]  # x0, y0, w, h
    image: np.ndarray  # masked image, full frame, uint8
    flow: FlowPair | None = None
    next_smpl: object | None = None
    next_time: float | None = None
    flow_magnitude: float = 0.0  # mean |flow| over valid pixels (px), for reporting
    extras: dict = field(default_factory=dict)


def crop_box(mask: np.ndarray | None, width: int, height: int, margin: int) -> tuple[int, int, int, int]:
    """The mask's bounding box plus ``margin`` pixels, inside the image; the whole image without a mask."""
    if mask is None or not mask.any():
        return 0, 0, width, height
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    x0 = max(int(cols[0]) - margin, 0)
    y0 = max(int(rows[0]) - margin, 0)
    x1 = min(int(cols[-1]) + 1 + margin, width)
    y1 = min(int(rows[-1]) + 1 + margin, height)
    # At least 16 px each way, so SSIM's window fits.
    if x1 - x0 < 16:
        x0, x1 = max(0, min(x0, width - 16)), min(width, max(x1, 16))
    if y1 - y0 < 16:
        y0, y1 = max(0, min(y0, height - 16)), min(height, max(y1, 16))
    return x0, y0, x1 - x0, y1 - y0


class FrameStore:
    """The frames the trainer learns from (bounded with ``capacity`` > 0)."""

    def __init__(
        self,
        *,
        capacity: int = 0,
        crop_margin: int = 16,
        flow: bool = True,
        flow_cache: FlowCache | None = None,
        flow_settings: FlowSettings | None = None,
        seed: int = 0,
    ):
        self.capacity = int(capacity)
        self.crop_margin = int(crop_margin)
        self.flow_enabled = flow
        self.flow_cache = flow_cache
        self.flow_settings = flow_settings or (flow_cache.settings if flow_cache else FlowSettings())
        self.frames: list[StoredFrame] = []
        self.seen = 0
        self._rng = np.random.default_rng(seed)
        self._last: dict[str, StoredFrame] = {}  # each camera's previous frame, for its flow

    def __len__(self) -> int:
        return len(self.frames)

    def add(self, frame: TrainFrame) -> StoredFrame:
        frame.check()
        if frame.mask is not None:
            image = np.where(frame.mask[..., None] > 127, frame.image, 0).astype(np.uint8)
        else:  # a writable copy (frames from the bus are read-only views)
            image = np.array(frame.image)
        crop = crop_box(frame.mask, int(frame.camera.width), int(frame.camera.height), self.crop_margin)
        stored = StoredFrame(frame, crop, image)
        prev = self._last.get(frame.camera.name)
        if (
            self.flow_enabled
            and prev is not None
            and frame.index == prev.frame.index + 1
            and frame.camera.name == prev.frame.camera.name
            and prev.image.shape == image.shape
        ):
            prev.flow = self._flow(prev, stored)
            prev.next_smpl = frame.smpl
            prev.next_time = frame.time
            valid = prev.flow.valid_forward
            if valid.any():
                prev.flow_magnitude = float(np.linalg.norm(prev.flow.forward[valid], axis=1).mean())
        self._last[frame.camera.name] = stored
        self.seen += 1
        if self.capacity <= 0 or len(self.frames) < self.capacity:
            self.frames.append(stored)
        else:  # reservoir sampling: every frame of the stream is kept with equal probability
            slot = int(self._rng.integers(0, self.seen))
            if slot < self.capacity:
                self.frames[slot] = stored
        return stored

    def _flow(self, a: StoredFrame, b: StoredFrame) -> FlowPair:
        ma, mb = a.frame.mask, b.frame.mask
        if self.flow_cache is not None:
            return self.flow_cache.get(a.image, b.image, ma, mb)
        return compute_flow_pair(a.image, b.image, ma, mb, self.flow_settings)
