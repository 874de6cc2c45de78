"""Offline tracking of a rig's recordings: what ``stg-track CAM1.mp4 CAM2.mp4 --calibration rig.json``
and ``stg-train --format video --calibration rig.json`` run.

- :func:`track_rig_to_file`: one video (or image folder) per camera, in the rig's camera order,
  -> POSES.npz in the rig's world frame (the single-camera contract, plus ``cameras``: the
  camera names, and ``camera_frames``: which frame of each input every row used), and masks per
  camera when asked. Frames are matched by time stamp first (sync.py): unsynchronised inputs
  fail before any tracking, saying by how much they drift.
- :func:`track_rig`: the same into a cache folder keyed by every input's content, the rig file
  and the options (a second run costs the hashing).
- :func:`rig_to_folder`: the tracked rig as a folder-format dataset (docs/DATASETS.md), every
  camera with its calibration, only the confident instants, for training.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from stg_node.calibration.rig import Rig, read_rig
from stg_node.progress import progress as progress_bar
from stg_node.tracking.pipeline import (
    DEFAULT_MIN_CONFIDENCE,
    JPEG_QUALITY,
    TrackOptions,
    TrackSummary,
    _options_digest,
    cache_root,
    input_digest,
)
from stg_node.tracking.poses_file import TrackedPoses, read_poses, write_poses

log = logging.getLogger(__name__)


def select_cameras(rig: Rig, inputs: Sequence, cameras: Sequence[str] | None) -> Rig:
    """The rig's cameras the inputs belong to: ``cameras`` names them in input order; without it,
    the inputs are the rig's cameras in the file's order (the counts must agree)."""
    if cameras:
        if len(cameras) != len(inputs):
            raise ValueError(f"--cameras names {len(cameras)} cameras for {len(inputs)} inputs")
        return rig.select(list(cameras))
    if len(inputs) != len(rig):
        raise ValueError(
            f"{len(inputs)} inputs for a rig of {len(rig)} cameras ({', '.join(rig.names)}): give one input "
            "per camera in that order, or name the inputs' cameras with --cameras"
        )
    return rig


def build_multiview_tracker(options: TrackOptions, rig: Rig, threads: int | None = None):
    """A :class:`~stg_node.tracking.multiview.MultiViewTracker` for ``rig`` and the body it fits."""
    from stg_node.body import load_body_model
    from stg_node.tracking.detectors import make_detector
    from stg_node.tracking.masks import make_masker
    from stg_node.tracking.multiview import MultiViewConfig, MultiViewTracker

    body = load_body_model(options.smpl_model)
    detectors = [
        make_detector(options.detector, model=options.pose_model, threads=threads) for _ in rig.cameras
    ]
    maskers = []
    for camera in rig.cameras:
        plate = None
        if options.mask_method() == "plate":
            from stg_node.data.io import read_image

            if options.plate is None or not Path(options.plate).is_dir():
                raise ValueError(
                    "--mask-method plate with a rig needs --plate DIR holding NAME.png per camera"
                )
            plate = read_image(Path(options.plate) / f"{camera.name}.png")
        maskers.append(make_masker(options.mask_method(), plate=plate))
    config = MultiViewConfig(max_side=options.max_side, smoothing=options.smoothing)
    return MultiViewTracker(detectors, body, rig, config, maskers), body


def track_rig_to_file(
    inputs: Sequence[str | Path],
    rig: Rig | str | Path,
    out: str | Path,
    options: TrackOptions | None = None,
    *,
    cameras: Sequence[str] | None = None,
    masks_dir: str | Path | None = None,
    max_skew_s: float | None = None,
    progress: bool = True,
    threads: int | None = None,
) -> TrackSummary:
    """Track a rig's recordings into POSES.npz (world frame) and, with ``masks_dir``, masks in
    ``masks_dir/NAME/{row:06d}.png``."""
    from stg_node.tracking.sync import match_sources, open_sources, synced_frames

    options = options or TrackOptions()
    rig = read_rig(rig) if not isinstance(rig, Rig) else rig
    rig = select_cameras(rig, inputs, cameras)
    sources = open_sources(inputs, options.fps)
    for source, camera in zip(sources, rig.cameras, strict=True):
        if (source.width, source.height) != camera.image_size:
            raise ValueError(
                f"{source.path}: {source.width}x{source.height} frames, but camera {camera.name} was "
                f"calibrated at {camera.width}x{camera.height} (record at the calibrated size, or calibrate "
                "again)"
            )
    match = match_sources(sources, rig.names, max_skew_s)
    tracker, body = build_multiview_tracker(options, rig, threads)
    if masks_dir is not None:
        masks_dir = Path(masks_dir)
        for name in rig.names:
            (masks_dir / name).mkdir(parents=True, exist_ok=True)
    rows: dict[str, list] = {k: [] for k in ("poses", "Rh", "Th", "confidence", "times", "rms", "frames")}
    started = time.perf_counter()
    bar = progress_bar(total=len(match), unit="instant", desc="stg-track (rig)", enabled=progress)
    try:
        for frame_set in synced_frames(sources, match):
            estimate = tracker.estimate([f.image for f in frame_set.frames], frame_set.time)
            smpl = estimate.smpl
            rows["poses"].append(np.asarray(smpl.poses, np.float32).reshape(72))
            rows["Rh"].append(smpl.Rh)
            rows["Th"].append(smpl.Th)
            rows["confidence"].append(estimate.confidence)
            rows["times"].append(frame_set.time)
            rows["rms"].append(estimate.reprojection_px)
            rows["frames"].append([f.index for f in frame_set.frames])
            if masks_dir is not None:
                for name, mask in zip(rig.names, estimate.masks, strict=True):
                    path = masks_dir / name / f"{frame_set.index:06d}.png"
                    if not cv2.imwrite(str(path), mask):
                        raise OSError(f"could not write the mask {path}")
            bar.update(1)
            bar.set_postfix(conf=f"{estimate.confidence:.2f}", views=estimate.views_used, refresh=False)
    finally:
        bar.close()
    if not rows["poses"]:
        raise ValueError("the rig's recordings hold no instant to track")
    count = len(rows["poses"])
    first = rig.cameras[0]
    tracked = TrackedPoses(
        poses=np.stack(rows["poses"]),
        Rh=np.stack(rows["Rh"]),
        Th=np.stack(rows["Th"]),
        shapes=np.tile(tracker.fitter.betas.astype(np.float32), (count, 1)),  # the calibrated shape
        confidence=np.asarray(rows["confidence"], np.float32),
        frames=np.arange(count, dtype=np.int64),
        times=np.asarray(rows["times"], np.float64),
        K=first.K,
        dist=first.dist,
        image_size=first.image_size,
        fps=1.0 / float(np.median(np.diff(match.times))) if count > 1 else 0.0,
        body=str(body.name),
        reprojection_px=np.asarray(rows["rms"], np.float32),
        cameras=tuple(rig.names),
        camera_frames=np.asarray(rows["frames"], np.int64),
    )
    write_poses(out, tracked)
    confidence = tracked.confidence
    return TrackSummary(
        out=Path(out),
        frames=count,
        confident_frames=int((confidence >= 0.5).sum()),
        mean_confidence=float(confidence.mean()),
        seconds=time.perf_counter() - started,
    )


def track_rig(
    inputs: Sequence[str | Path],
    rig_path: str | Path,
    options: TrackOptions | None = None,
    *,
    cameras: Sequence[str] | None = None,
    cache_dir: str | Path | None = None,
    max_skew_s: float | None = None,
    progress: bool = True,
    threads: int | None = None,
) -> Path:
    """Track a rig once and cache the result; returns ``CACHE/<key>/POSES.npz`` (masks/NAME/ beside it)."""
    options = options or TrackOptions()
    digest = hashlib.sha256()
    for path in inputs:
        digest.update(input_digest(path).encode())
    digest.update(Path(rig_path).read_bytes())
    digest.update(f"{_options_digest(options)}:{list(cameras or [])}:{max_skew_s}:rig".encode())
    key = digest.hexdigest()[:24]
    root = Path(cache_dir) if cache_dir is not None else cache_root()
    entry = root / key
    poses = entry / "POSES.npz"
    if poses.is_file():
        log.info("tracking of the rig found in the cache: %s", poses)
        return poses
    root.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{key}.", dir=root))
    try:
        track_rig_to_file(
            inputs,
            rig_path,
            staging / "POSES.npz",
            options,
            cameras=cameras,
            masks_dir=staging / "masks",
            max_skew_s=max_skew_s,
            progress=progress,
            threads=threads,
        )
        (staging / "source.json").write_text(
            json.dumps({"inputs": [str(Path(p).resolve()) for p in inputs], "rig": str(rig_path)}, indent=2)
            + "\n"
        )
        try:
            os.replace(staging, entry)
        except OSError:
            if not poses.is_file():
                raise
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)
    return poses


def rig_to_folder(
    inputs: Sequence[str | Path],
    rig_path: str | Path,
    out: str | Path,
    options: TrackOptions | None = None,
    *,
    cameras: Sequence[str] | None = None,
    min_confidence: float = DEFAULT_MIN_CONFIDENCE,
    cache_dir: str | Path | None = None,
    progress: bool = True,
    threads: int | None = None,
) -> Path:
    """A rig's recordings as a folder-format dataset under ``out``: ``cameras.json`` (the rig's
    calibration: K, D = dist, R, t, size), ``images/NAME/{row:06d}.jpg``, ``masks/NAME/...png`` and
    ``poses.npz`` (world frame) for the instants tracked with confidence >= ``min_confidence``."""
    from stg_node.tracking.sync import match_sources, open_sources, synced_frames

    if not 0.0 <= min_confidence <= 1.0:
        raise ValueError(f"min_confidence must lie in [0, 1], got {min_confidence}")
    options = options or TrackOptions()
    rig = select_cameras(read_rig(rig_path), inputs, cameras)
    poses_path = track_rig(
        inputs, rig_path, options, cameras=cameras, cache_dir=cache_dir, progress=progress, threads=threads
    )
    tracked = read_poses(poses_path)
    keep = tracked.confidence >= min_confidence
    if not keep.any():
        raise ValueError(
            f"no instant of the rig was tracked with confidence >= {min_confidence} (best "
            f"{tracked.confidence.max():.2f}); is one person in view of the cameras, whole and well lit?"
        )
    out = Path(out)
    for name in rig.names:
        (out / "images" / name).mkdir(parents=True, exist_ok=True)
        (out / "masks" / name).mkdir(parents=True, exist_ok=True)
    wanted = set(np.flatnonzero(keep).tolist())
    sources = open_sources(inputs, options.fps)
    match = match_sources(sources, rig.names)
    for frame_set in synced_frames(sources, match):
        if frame_set.index not in wanted:
            continue
        name_png = f"{frame_set.index:06d}.png"
        for camera, frame in zip(rig.cameras, frame_set.frames, strict=True):
            target = out / "images" / camera.name / f"{frame_set.index:06d}.jpg"
            bgr = cv2.cvtColor(frame.image, cv2.COLOR_RGB2BGR)
            if not cv2.imwrite(str(target), bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY]):
                raise OSError(f"could not write {target}")
            shutil.copyfile(
                poses_path.parent / "masks" / camera.name / name_png, out / "masks" / camera.name / name_png
            )
    calibration = {
        c.name: {
            "K": c.K.tolist(),
            "D": c.dist.tolist() if c.dist.size else [0.0] * 5,
            "R": c.R.tolist(),
            "t": c.t.tolist(),
            "width": c.width,
            "height": c.height,
        }
        for c in rig.cameras
    }
    (out / "cameras.json").write_text(json.dumps({"fps": tracked.fps, "cameras": calibration}, indent=2))
    np.savez(
        out / "poses.npz",
        poses=tracked.poses[keep],
        Rh=tracked.Rh[keep],
        Th=tracked.Th[keep],
        shapes=tracked.shapes[keep],
        frames=tracked.frames[keep],
        times=tracked.times[keep],
    )
    log.info("rig: %d of %d instants confident enough for training -> %s", keep.sum(), len(keep), out)
    return out
