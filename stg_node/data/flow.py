"""Optical flow between consecutive training frames: OpenCV DIS, both directions, masked, cached.

STG-Avatar's flow loss and flow-guided densification need, for each pair of consecutive frames
of the training camera, where each person pixel moves (forward ``t -> t+1`` and backward) and
which of those vectors to trust. This module computes them with DIS (Kroeger et al. 2016; fast
and good on textured clothing), restricted to the person:

- flow is computed on the bounding box of both masks plus a margin (the person often covers a
  third of the frame; the rest is black background, wasted work);
- a vector is valid where its source pixel is on the person, it lands inside the image and on
  the person in the other frame, and it passes the forward-backward consistency test of
  Sundaram et al. (2010): ``|F(x) + B(x + F(x))|^2 < a (|F|^2 + |B|^2) + b`` (a = 0.01, b = 0.5);
- outside the valid region flow is zero.

Results are cached on disk under a key that hashes the input pixels, masks and every setting, so
a changed frame, mask or preset never reuses a stale flow; a corrupt cache file is recomputed.
"""

from __future__ import annotations

import hashlib
import logging
import os
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from stg_node.safe_load import load_npz

log = logging.getLogger(__name__)

PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}
CACHE_VERSION = 3  # bump when the computation changes, so old cache files are not reused


@dataclass(frozen=True)
class FlowSettings:
    preset: str = "fast"
    consistency_alpha: float = 0.01
    consistency_beta: float = 0.5  # px^2
    crop_margin: int = 32  # px around the union of both masks
    # DIS's finest pyramid level (0: the frames' own pixels; None: the preset's, 2 for ultrafast and
    # fast, a quarter of the resolution). The flow is read against thresholds in pixels of the frames
    # (the missed-motion test, the seeds' consistency), and a level-s flow is upsampled 2^s x with its
    # error: on the synthetic still subject at 256 px, |DIS - true flow| averaged 0.74 px at level 2
    # (as large as its true motion, 1.06 px), 0.42 at level 1 and 0.25 at level 0 (docs/AVATAR.md).
    finest_scale: int | None = 0

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise ValueError(f"preset must be one of {sorted(PRESETS)}, got {self.preset!r}")
        if self.finest_scale is not None and not 0 <= self.finest_scale <= 8:
            raise ValueError(f"finest_scale must be None or 0..8, got {self.finest_scale!r}")


@dataclass(frozen=True)
class FlowPair:
    """Flow between frames ``a`` and ``b`` of one camera, in pixels of the delivered images."""

    forward: np.ndarray  # (H, W, 2) float32: pixel x of a moves to x + forward[x] in b
    backward: np.ndarray  # (H, W, 2) float32: pixel x of b comes from x + backward[x] in a
    valid_forward: np.ndarray  # (H, W) bool: forward vectors to trust
    valid_backward: np.ndarray  # (H, W) bool


def _gray(image: np.ndarray) -> np.ndarray:
    """8-bit grey image for DIS; float images are taken to be in [0, 1]."""
    if image.dtype != np.uint8:
        image = np.clip(np.rint(np.asarray(image, np.float64) * 255.0), 0, 255).astype(np.uint8)
    if image.ndim == 2:
        return np.ascontiguousarray(image)
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


def dis_flow(
    src: np.ndarray, dst: np.ndarray, preset: str = "fast", finest_scale: int | None = None
) -> np.ndarray:
    """Dense DIS flow ``(H, W, 2)`` from ``src`` to ``dst`` (RGB or grey uint8); ``finest_scale``: the
    pyramid level it stops at (None: the preset's)."""
    dis = cv2.DISOpticalFlow_create(PRESETS[preset])
    if finest_scale is not None:
        dis.setFinestScale(int(finest_scale))
    return dis.calc(_gray(src), _gray(dst), None)


def _consistency(
    flow_ab: np.ndarray, flow_ba: np.ndarray, mask_b: np.ndarray, settings: FlowSettings
) -> np.ndarray:
    """Where flow a->b is confirmed by flow b->a and lands on the person in b (so inside the image)."""
    h, w = flow_ab.shape[:2]
    fx, fy = cv2.split(flow_ab)  # contiguous planes: arithmetic on them is several times faster
    map_x = fx + np.arange(w, dtype=np.float32)
    map_y = fy + np.arange(h, dtype=np.float32)[:, None]
    back = cv2.remap(flow_ba, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    # nearest sampling with a zero border: False off the image as well as off the person
    landed = cv2.remap(mask_b, map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    bx, by = cv2.split(back)
    ex, ey = fx + bx, fy + by
    err = ex * ex + ey * ey
    bound = fx * fx + fy * fy + bx * bx + by * by
    bound *= settings.consistency_alpha
    bound += settings.consistency_beta
    return (landed > 0) & (err < bound)


def _as_mask(mask: np.ndarray) -> np.ndarray:
    """uint8 mask (non-zero = person), as OpenCV's remap and boundingRect need."""
    mask = np.asarray(mask)
    return mask if mask.dtype == np.uint8 else (mask > 0).astype(np.uint8) * np.uint8(255)


def _crop_box(mask_a: np.ndarray, mask_b: np.ndarray, margin: int) -> tuple[int, int, int, int]:
    h, w = mask_a.shape
    x, y, bw, bh = cv2.boundingRect(cv2.bitwise_or(mask_a, mask_b))
    if bw == 0 or bh == 0:
        return 0, 0, 0, 0
    return max(x - margin, 0), max(y - margin, 0), min(x + bw + margin, w), min(y + bh + margin, h)


def compute_flow_pair(
    image_a: np.ndarray,
    image_b: np.ndarray,
    mask_a: np.ndarray | None = None,
    mask_b: np.ndarray | None = None,
    settings: FlowSettings | None = None,
) -> FlowPair:
    """Forward and backward flow with validity masks; masks None means the whole image is the person."""
    settings = settings or FlowSettings()
    if image_a.shape != image_b.shape:
        raise ValueError(f"frames differ in shape: {image_a.shape} vs {image_b.shape}")
    h, w = image_a.shape[:2]
    full = np.full((h, w), 255, np.uint8)
    mask_a = full if mask_a is None else mask_a
    mask_b = full if mask_b is None else mask_b
    if mask_a.shape != (h, w) or mask_b.shape != (h, w):
        raise ValueError(f"masks must be {(h, w)}, got {mask_a.shape} and {mask_b.shape}")
    mask_a, mask_b = _as_mask(mask_a), _as_mask(mask_b)
    forward = np.zeros((h, w, 2), np.float32)
    backward = np.zeros((h, w, 2), np.float32)
    valid_f = np.zeros((h, w), bool)
    valid_b = np.zeros((h, w), bool)
    x0, y0, x1, y1 = _crop_box(mask_a, mask_b, settings.crop_margin)
    if x1 - x0 >= 8 and y1 - y0 >= 8:  # DIS needs a few patches; an empty mask yields no flow
        crop = (slice(y0, y1), slice(x0, x1))
        ga, gb = _gray(image_a)[crop], _gray(image_b)[crop]
        ma, mb = mask_a[crop], mask_b[crop]
        f = dis_flow(ga, gb, settings.preset, settings.finest_scale)
        b = dis_flow(gb, ga, settings.preset, settings.finest_scale)
        vf = _consistency(f, b, mb, settings) & (ma > 0)
        vb = _consistency(b, f, ma, settings) & (mb > 0)
        f *= vf[..., None]  # zero where untrusted (a multiply is ~10x cheaper than masked writes)
        b *= vb[..., None]
        forward[crop] = f
        backward[crop] = b
        valid_f[crop] = vf
        valid_b[crop] = vb
    return FlowPair(forward, backward, valid_f, valid_b)


class FlowCache:
    """Flow pairs stored as compressed .npz files in ``directory``, keyed by inputs and settings."""

    def __init__(self, directory: str | Path, settings: FlowSettings | None = None):
        self.directory = Path(directory)
        self.settings = settings or FlowSettings()
        self.hits = 0
        self.misses = 0
        self.dropped = 0  # unreadable cache files that were recomputed

    def key(self, image_a, image_b, mask_a, mask_b) -> str:
        digest = hashlib.sha256()
        digest.update(repr((CACHE_VERSION, self.settings, cv2.__version__)).encode())
        for array in (image_a, image_b, mask_a, mask_b):
            if array is None:
                digest.update(b"none")
                continue
            array = np.ascontiguousarray(array)
            digest.update(repr((array.shape, array.dtype.str)).encode())
            digest.update(array.data)
        return digest.hexdigest()[:32]

    def path(self, key: str) -> Path:
        return self.directory / f"flow_{key}.npz"

    def get(self, image_a, image_b, mask_a=None, mask_b=None) -> FlowPair:
        key = self.key(image_a, image_b, mask_a, mask_b)
        path = self.path(key)
        if path.is_file():
            try:
                pair = self._read(path, image_a.shape[:2])
            except Exception as exc:  # truncated or foreign file: recompute, never crash training
                self.dropped += 1
                log.warning("flow cache file %s unreadable (%s); recomputing", path, exc)
            else:
                self.hits += 1
                return pair
        self.misses += 1
        pair = compute_flow_pair(image_a, image_b, mask_a, mask_b, self.settings)
        self._write(path, pair)
        return pair

    @staticmethod
    def _read(path: Path, shape: tuple[int, int]) -> FlowPair:
        data = load_npz(path)
        pair = FlowPair(
            forward=data["forward"].astype(np.float32),
            backward=data["backward"].astype(np.float32),
            valid_forward=data["valid_forward"].astype(bool),
            valid_backward=data["valid_backward"].astype(bool),
        )
        if pair.forward.shape != (*shape, 2) or pair.valid_forward.shape != shape:
            raise ValueError(f"shape {pair.forward.shape} does not match frames {shape}")
        return pair

    def _write(self, path: Path, pair: FlowPair) -> None:
        self.directory.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=self.directory, suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as fh:
                np.savez_compressed(
                    fh,
                    forward=pair.forward,
                    backward=pair.backward,
                    valid_forward=pair.valid_forward,
                    valid_backward=pair.valid_backward,
                )
            os.replace(tmp, path)  # atomic: a crash never leaves a half-written cache file
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)


def consecutive_pairs(dataset, camera: str | None = None) -> list[tuple[int, int]]:
    """(frame, next frame) pairs of one camera of a dataset split, in frame order."""
    camera = camera or dataset.camera_names[0]
    frames = sorted({v.frame for v in dataset.views if v.camera == camera})
    return list(zip(frames[:-1], frames[1:], strict=True))


def sequence_flows(dataset, cache: FlowCache, camera: str | None = None, progress: bool = True) -> dict:
    """``{(frame_a, frame_b): FlowPair}`` for consecutive frames of one camera."""
    from stg_node.progress import progress as progress_bar

    camera = camera or dataset.camera_names[0]
    pairs: Sequence[tuple[int, int]] = consecutive_pairs(dataset, camera)
    out = {}
    previous = None
    for a, b in progress_bar(pairs, desc="optical flow", unit="pair", enabled=progress):
        sample_a = previous if previous is not None and previous.index == a else dataset.load(a, camera)
        sample_b = dataset.load(b, camera)
        out[(a, b)] = cache.get(sample_a.image, sample_b.image, sample_a.mask, sample_b.mask)
        previous = sample_b
    return out
