"""Offline tracking of a whole video or image folder: what ``stg-track`` and ``stg-train --format video`` run.

- :func:`track_to_file`: input -> POSES.npz (+ optional masks folder and fit preview), with a
  progress bar. Without a calibration or a given field of view, the focal length is estimated
  from the sequence (focal.py): the first pass tracks at the default field of view and keeps
  each frame's keypoints; when the estimate is sure, a second pass re-fits those keypoints and
  the first pass's person masks with it (nothing is detected twice). Frames that cannot be
  trusted (frame_checks.py, tracker.py) are counted by reason.
- :func:`track_video`: the same into a cache folder keyed by the input's content and every
  setting that changes the result, so running it twice on the same video costs one hash.
  It returns the path of POSES.npz; the masks are ``masks/{frame:06d}.png`` beside it.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import os
import shutil
import tempfile
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

import stg_node
from stg_node.offline_assets import sha256_file
from stg_node.progress import progress as progress_bar
from stg_node.tracking.camera import DEFAULT_FOV_DEG, Intrinsics, from_fov, load_intrinsics
from stg_node.tracking.fitting import FitConfig
from stg_node.tracking.poses_file import TrackedPoses, write_poses
from stg_node.tracking.sources import ImageFolderSource, open_source

log = logging.getLogger(__name__)

ENV_CACHE = "STG_TRACK_CACHE"
CACHE_FORMAT = 2  # bump when the output of the same input and settings changes
# The code whose edits change the tracked poses: an edited fit or keypoint layout tracks afresh
# (a version number is not bumped by every commit, and a stale entry hid a tracker change once).
TRACKING_CODE = ("tracking", "body")


@dataclass(frozen=True)
class TrackOptions:
    """Everything besides the input that decides the output."""

    intrinsics: str | None = None  # JSON file with K (and dist); None: pinhole from fov_deg
    fov_deg: float | None = None  # horizontal field of view; None: estimated from the footage (focal.py)
    smpl_model: str | None = None  # SMPL .pkl/.npz file or folder; None: the open body
    detector: str = "blazepose"
    pose_model: str | None = None  # ONNX file (detector "onnx") or a folder with the BlazePose files
    mask: str | None = None  # None: "segmentation" for blazepose, "mog2" otherwise
    plate: str | None = None  # empty-plate image for mask "plate"
    fps: float | None = None  # frame rate of an image folder (videos carry their own)
    max_side: int = 512
    smoothing: bool = True

    def mask_method(self) -> str:
        if self.mask is not None:
            return self.mask
        return "segmentation" if self.detector == "blazepose" else "mog2"


@dataclass(frozen=True)
class TrackSummary:
    out: Path
    frames: int
    confident_frames: int  # confidence >= 0.5
    mean_confidence: float
    seconds: float
    skipped: dict[str, int] = field(default_factory=dict)  # reason -> frames below 0.5 with it
    camera: str = ""  # where K came from, in words

    def describe_skipped(self) -> str:
        """``"12 frames skipped: 8 cut_by_border, 4 motion_blur"`` (a frame may have several reasons)."""
        count = self.frames - self.confident_frames
        if not count:
            return "no frame skipped"
        reasons = ", ".join(f"{n} {why}" for why, n in sorted(self.skipped.items(), key=lambda kv: -kv[1]))
        return f"{count} of {self.frames} frames skipped (confidence < {DEFAULT_MIN_CONFIDENCE}): {reasons}"


def skip_reasons(confidence: np.ndarray, flags, threshold: float = 0.5) -> dict[str, int]:
    """Reason -> frames below ``threshold`` that carry it (``low_confidence`` when none is named)."""
    counts: dict[str, int] = {}
    for conf, text in zip(confidence, flags, strict=True):
        if conf >= threshold:
            continue
        for why in [w for w in str(text).split(",") if w] or ["low_confidence"]:
            counts[why] = counts.get(why, 0) + 1
    return counts


def input_digest(path: str | Path) -> str:
    """SHA-256 of a video file's bytes, or of an image folder's image names and bytes."""
    path = Path(path)
    digest = hashlib.sha256()
    if path.is_dir():
        for file in ImageFolderSource(path).files:
            digest.update(file.name.encode() + b"\0")
            sha256_file(file, digest)
    else:
        sha256_file(path, digest)
    return digest.hexdigest()


def _options_digest(options: TrackOptions) -> str:
    described = asdict(options)
    described["mask"] = options.mask_method()
    for key in ("intrinsics", "smpl_model", "pose_model", "plate"):
        value = described[key]
        if value is not None and Path(value).is_file():
            described[key] = {"name": Path(value).name, "sha256": sha256_file(Path(value)).hexdigest()}
    described["stg_node"] = stg_node.__version__
    described["format"] = CACHE_FORMAT
    described["fit"] = asdict(FitConfig())  # new fit defaults (a silhouette term) track afresh
    described["code"] = tracking_code_digest()
    return hashlib.sha256(json.dumps(described, sort_keys=True, default=str).encode()).hexdigest()


@functools.cache
def tracking_code_digest(packages: tuple[str, ...] = TRACKING_CODE) -> str:
    """SHA-256 over the Python sources of these stg_node subpackages (names and bytes, sorted)."""
    digest = hashlib.sha256()
    root = Path(stg_node.__file__).parent
    for package in packages:
        for source in sorted((root / package).rglob("*.py")):
            digest.update(source.relative_to(root).as_posix().encode())
            digest.update(source.read_bytes())
    return digest.hexdigest()


def cache_root() -> Path:
    if os.environ.get(ENV_CACHE):
        return Path(os.environ[ENV_CACHE]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "stg_node" / "track"


def build_tracker(
    options: TrackOptions,
    width: int,
    height: int,
    threads: int | None = None,
    *,
    intrinsics: Intrinsics | None = None,
    fit: FitConfig | None = None,
):
    """The Tracker for frames of ``width x height`` and these options (loads the networks).

    ``intrinsics``: the camera, when the caller knows it (the tracker node: a camera/frame's
    ``K``); else from ``options`` (a calibration file or the field of view). ``fit``: the SMPL
    fit's settings (default: FitConfig())."""
    from stg_node.body import load_body_model
    from stg_node.tracking.detectors import make_detector
    from stg_node.tracking.masks import make_masker
    from stg_node.tracking.tracker import Tracker, TrackerConfig

    if intrinsics is None:
        intrinsics = camera_for(options, width, height)
    elif (intrinsics.width, intrinsics.height) != (width, height):
        raise ValueError(
            f"intrinsics are for {intrinsics.width}x{intrinsics.height} frames, not {width}x{height}"
        )
    body = load_body_model(options.smpl_model)
    detector = make_detector(options.detector, model=options.pose_model, threads=threads)
    plate = None
    if options.plate is not None:
        from stg_node.data.io import read_image

        plate = read_image(options.plate)
    masker = make_masker(options.mask_method(), plate=plate)
    config = TrackerConfig(max_side=options.max_side, smoothing=options.smoothing, fit=fit or FitConfig())
    return Tracker(detector, body, intrinsics, config, masker), body


def camera_for(options: TrackOptions, width: int, height: int) -> Intrinsics:
    if options.intrinsics is not None:
        return load_intrinsics(options.intrinsics, width, height)
    return from_fov(width, height, DEFAULT_FOV_DEG if options.fov_deg is None else options.fov_deg)


def track_to_file(
    input_path: str | Path,
    out: str | Path,
    options: TrackOptions | None = None,
    *,
    masks_dir: str | Path | None = None,
    preview: str | Path | None = None,
    progress: bool = True,
    threads: int | None = None,
) -> TrackSummary:
    """Track every frame of a video or image folder; write POSES.npz (and masks, and the fit preview,
    when asked). See the module docstring for the focal length and the frames that are skipped."""
    import time

    from stg_node.tracking.focal import FocalObservation, estimate_focal
    from stg_node.tracking.frame_checks import image_factor

    options = options or TrackOptions()
    source = open_source(input_path, options.fps)
    tracker, body = build_tracker(options, source.width, source.height, threads)
    estimate_camera = options.intrinsics is None and options.fov_deg is None
    scratch = None
    if masks_dir is None and (preview is not None or estimate_camera):
        # The preview draws the masks; a second pass at the estimated focal length fits to them.
        scratch = tempfile.TemporaryDirectory(prefix="stg-track-masks-")
        masks_dir = scratch.name
    if masks_dir is not None:
        masks_dir = Path(masks_dir)
        masks_dir.mkdir(parents=True, exist_ok=True)
    rows: dict[str, list] = {
        k: [] for k in ("poses", "Rh", "Th", "shapes", "confidence", "frames", "times", "rms", "flags")
    }
    observations: list[FocalObservation | None] = []
    shape = (source.height, source.width)
    t0 = time.perf_counter()
    bar = progress_bar(total=len(source) or None, unit="frame", desc="stg-track", enabled=progress)
    try:
        for frame in source:
            estimate = tracker.estimate(frame.image, frame.timestamp)
            _append(rows, estimate, frame.index, frame.timestamp)
            if estimate_camera:
                kp = estimate.keypoints
                observations.append(
                    None
                    if kp is None
                    else FocalObservation(
                        frame.timestamp, replace(kp, segmentation=None), estimate.confidence
                    )
                )
            if masks_dir is not None:
                path = masks_dir / f"{frame.index:06d}.png"
                if not cv2.imwrite(str(path), estimate.mask):
                    raise OSError(f"could not write the mask {path}")
            bar.update(1)
            bar.set_postfix(conf=f"{estimate.confidence:.2f}", refresh=False)
    finally:
        bar.close()
    if not rows["poses"]:
        raise ValueError(f"{input_path}: no frames to track")
    intrinsics = tracker.intrinsics
    betas = tracker.fitter.betas
    camera = {"method": "file", "path": str(options.intrinsics)} if options.intrinsics else None
    if options.fov_deg is not None:
        camera = {"method": "fov", "fov_deg": float(options.fov_deg)}
    if estimate_camera:
        found = estimate_focal(
            [o for o in observations if o is not None], body, tracker.layout, source.width, source.height
        )
        log.info("%s", found.describe())
        camera = {"method": "estimate", **json.loads(found.to_json()), "used": "default"}
        if found.sure:
            camera["used"] = "estimate"
            intrinsics = from_fov(source.width, source.height, found.fov_deg)
            rows, betas = _refit(
                tracker, body, intrinsics, rows, observations, shape, image_factor, masks_dir
            )
        else:
            log.warning(
                "the field of view stays at the default %g degrees: %s (give --fov or --intrinsics)",
                DEFAULT_FOV_DEG,
                found.reason,
            )
    tracked = TrackedPoses(
        poses=np.stack(rows["poses"]),
        Rh=np.stack(rows["Rh"]),
        Th=np.stack(rows["Th"]),
        shapes=np.stack(rows["shapes"]),
        confidence=np.asarray(rows["confidence"], np.float32),
        frames=np.asarray(rows["frames"], np.int64),
        times=np.asarray(rows["times"], np.float64),
        K=intrinsics.K,
        dist=np.zeros(0) if intrinsics.dist is None else intrinsics.dist,
        image_size=(source.width, source.height),
        fps=source.fps,
        body=str(body.name),
        reprojection_px=np.asarray(rows["rms"], np.float32),
        flags=np.asarray(rows["flags"], dtype=str),
        camera=json.dumps(camera),
    )
    # Shape calibration converges during the first frames: give every row the final shape.
    tracked.shapes[:] = np.asarray(betas, np.float32)
    write_poses(out, tracked)
    if preview is not None:
        from stg_node.tracking.preview import write_preview

        write_preview(input_path, out, preview, masks_dir=masks_dir, smpl_model=options.smpl_model,
                      fps=options.fps, progress=progress)  # fmt: skip
    if scratch is not None:
        scratch.cleanup()
    confidence = tracked.confidence
    return TrackSummary(
        out=Path(out),
        frames=len(tracked),
        confident_frames=int((confidence >= DEFAULT_MIN_CONFIDENCE).sum()),
        mean_confidence=float(confidence.mean()),
        seconds=time.perf_counter() - t0,
        skipped=skip_reasons(confidence, tracked.flags, DEFAULT_MIN_CONFIDENCE),
        camera=describe_camera(camera),
    )


def _append(rows: dict[str, list], estimate, index: int, timestamp: float) -> None:
    smpl = estimate.smpl
    rows["poses"].append(np.asarray(smpl.poses, np.float32).reshape(72))
    rows["Rh"].append(smpl.Rh)
    rows["Th"].append(smpl.Th)
    rows["shapes"].append(smpl.betas)
    rows["confidence"].append(estimate.confidence)
    rows["frames"].append(index)
    rows["times"].append(timestamp)
    rows["rms"].append(estimate.reprojection_px)
    rows["flags"].append(",".join(estimate.flags))


def _refit(tracker, body, intrinsics, rows, observations, shape, image_factor, masks_dir=None):
    """The second pass: the first pass's keypoints fitted with ``intrinsics``, refined by the first
    pass's person masks (``masks_dir``) as the first pass was; the image checks (border, blur) of the
    first pass carried over. Returns new rows and the calibrated shape.

    Without the masks the second pass lost the silhouette term: its poses were not the ones a first
    pass at that focal length gives. With them, a walk filmed at 45 degrees and re-fitted at 56.6
    trains like one tracked at 56.6 from the start (held-out frames 30.65 / LPIPS 0.0316 against
    30.58 / 0.0322; without the masks 31.08 / 0.0349; docs/BENCHMARKS.md, "The focal length from
    the footage: the estimate or the default")."""
    from stg_node.tracking.tracker import Tracker

    again = Tracker(tracker.detector, body, intrinsics, tracker.config, tracker.masker)
    new: dict[str, list] = {k: [] for k in rows}
    for i, obs in enumerate(observations):
        index, timestamp = rows["frames"][i], rows["times"][i]
        old_flags = [f for f in rows["flags"][i].split(",") if f]
        if obs is None:
            estimate = again.skip(shape, timestamp, tuple(old_flags))
        else:
            silhouette = _first_pass_silhouette(again, masks_dir, index)
            estimate = again.fit_keypoints(obs.keypoints, timestamp, shape, silhouette=silhouette)
            carried = [f for f in old_flags if f in ("cut_by_border", "motion_blur")]
            estimate = replace(
                estimate,
                confidence=float(estimate.confidence * image_factor(carried)),
                flags=tuple(f for f in estimate.flags if f not in carried) + tuple(carried),
            )
        _append(new, estimate, index, timestamp)
    return new, again.fitter.betas


def _first_pass_silhouette(tracker, masks_dir, index: int):
    """The silhouette function of :meth:`Tracker.fit_keypoints` from the first pass's mask of frame
    ``index`` (an RGB masker's mask does not depend on the fit's distance), or None: no mask kept,
    or a fit without the silhouette term."""
    if masks_dir is None or not tracker.fitter.uses_silhouette:
        return None
    mask = cv2.imread(str(Path(masks_dir) / f"{index:06d}.png"), cv2.IMREAD_GRAYSCALE)
    if mask is None:
        return None
    undistorted = tracker.intrinsics.undistort_mask(mask)
    return lambda fit: undistorted


def describe_camera(camera: dict | None) -> str:
    """Where the tracking's camera came from, in words (stg-track's and stg-train's report)."""
    if not camera:
        return ""
    if camera["method"] == "file":
        return f"camera from {camera['path']}"
    if camera["method"] == "fov":
        return f"camera: the given {camera['fov_deg']:g} degree field of view"
    interval = f"{camera['low_fov_deg']:.0f}-{camera['high_fov_deg']:.0f}"
    if camera["used"] == "estimate":
        return (
            f"camera: {camera['fov_deg']:.1f} degree field of view estimated from the footage "
            f"(68 % interval {interval} degrees, sure)"
        )
    return (
        f"camera: UNSURE of the field of view (estimate {camera['fov_deg']:.0f}, interval {interval} "
        f"degrees: {camera['reason']}); kept the default {DEFAULT_FOV_DEG:g} degrees: give --fov or "
        f"--intrinsics if you know it (--fov {camera['fov_deg']:.0f} trains with the estimate)"
    )


def track_video(
    path: str | Path,
    options: TrackOptions | None = None,
    *,
    cache_dir: str | Path | None = None,
    masks: bool = True,
    progress: bool = True,
    threads: int | None = None,
) -> Path:
    """Track ``path`` once and cache the result; returns ``CACHE/<key>/POSES.npz``.

    The key hashes the input's bytes and every option (files by content), so an edited video or
    another setting tracks anew. ``masks``: also write ``masks/{frame:06d}.png`` beside it. The
    cache entry appears atomically (built in a temporary folder, then renamed).
    """
    options = options or TrackOptions()
    path = Path(path)
    root = Path(cache_dir) if cache_dir is not None else cache_root()
    key = hashlib.sha256(f"{input_digest(path)}:{_options_digest(options)}:{masks}".encode()).hexdigest()[:24]
    return cached_poses(
        root,
        key,
        lambda staging: track_to_file(
            path,
            staging / "POSES.npz",
            options,
            masks_dir=staging / "masks" if masks else None,
            progress=progress,
            threads=threads,
        ),
        {"input": str(path.resolve()), "options": asdict(options)},
        what=str(path),
    )


def cached_poses(root: Path, key: str, track, source: dict, *, what: str) -> Path:
    """``root/<key>/POSES.npz``: returned when there; else ``track(staging)`` writes POSES.npz (and
    masks) into a temporary folder beside it, ``source`` goes into its source.json, and the folder
    is renamed into place, so an entry appears whole or not at all."""
    entry = root / key
    poses = entry / "POSES.npz"
    if poses.is_file():
        log.info("tracking of %s found in the cache: %s", what, poses)
        return poses
    root.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{key}.", dir=root))
    try:
        track(staging)
        (staging / "source.json").write_text(json.dumps(source, indent=2, default=str) + "\n")
        try:
            os.replace(staging, entry)
        except OSError:
            if not poses.is_file():  # a concurrent run may have filled it first: keep theirs
                raise
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)
    return poses


CAMERA_NAME = "camera"
DEFAULT_MIN_CONFIDENCE = 0.5
TRACKING_REPORT = "tracking.json"  # what video_to_folder kept and skipped, and the camera
JPEG_QUALITY = 95


def write_jpeg(path: Path, rgb: np.ndarray) -> None:
    """A training image of the folder format (JPEG_QUALITY)."""
    bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    if not cv2.imwrite(str(path), bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY]):
        raise OSError(f"could not write {path}")


def write_training_poses(path: Path, tracked, keep: np.ndarray) -> None:
    """The folder format's poses.npz: the ``keep`` rows of a tracking (docs/DATASETS.md)."""
    np.savez(
        path,
        poses=tracked.poses[keep],
        Rh=tracked.Rh[keep],
        Th=tracked.Th[keep],
        shapes=tracked.shapes[keep],
        frames=tracked.frames[keep],
        times=tracked.times[keep],
    )


def video_to_folder(
    source: str | Path,
    out: str | Path,
    options: TrackOptions | None = None,
    *,
    min_confidence: float = DEFAULT_MIN_CONFIDENCE,
    cache_dir: str | Path | None = None,
    progress: bool = True,
    threads: int | None = None,
) -> Path:
    """A video (or image folder) as a dataset in the folder format (docs/DATASETS.md), for training.

    Tracks ``source`` with :func:`track_video` (cached), then writes under ``out``:
    ``cameras.json`` (one camera ``"camera"``: the tracking's ``K``, its distortion as ``D``,
    ``R = I``, ``t = 0``: the world frame is the camera's), ``images/camera/{frame:06d}.jpg``,
    ``masks/camera/{frame:06d}.png`` and ``poses.npz`` (``poses``, ``Rh``, ``Th``, ``shapes``,
    ``frames``, ``times``) for the frames whose confidence is at least ``min_confidence``; the
    others are left out, so a trainer never sees them, and counted by reason in
    ``tracking.json`` (with where the camera came from). Returns ``out``.
    """
    from stg_node.tracking.poses_file import read_poses

    if not 0.0 <= min_confidence <= 1.0:
        raise ValueError(f"min_confidence must lie in [0, 1], got {min_confidence}")
    options = options or TrackOptions()
    poses_path = track_video(
        source, options, cache_dir=cache_dir, masks=True, progress=progress, threads=threads
    )
    tracked = read_poses(poses_path)
    keep = tracked.confidence >= min_confidence
    if not keep.any():
        raise ValueError(
            f"{source}: no frame was tracked with confidence >= {min_confidence} (best "
            f"{tracked.confidence.max():.2f}); is one person in view, whole and well lit?"
        )
    out = Path(out)
    images = out / "images" / CAMERA_NAME
    masks = out / "masks" / CAMERA_NAME
    for folder in (images, masks):
        folder.mkdir(parents=True, exist_ok=True)
    wanted = set(tracked.frames[keep].tolist())
    for frame in open_source(source, options.fps):
        if frame.index not in wanted:
            continue
        name = f"{frame.index:06d}"
        write_jpeg(images / f"{name}.jpg", frame.image)
        shutil.copyfile(poses_path.parent / "masks" / f"{name}.png", masks / f"{name}.png")
    width, height = tracked.image_size
    camera = {
        "K": tracked.K.tolist(),
        "R": np.eye(3).tolist(),
        "t": [0.0, 0.0, 0.0],
        "width": width,
        "height": height,
    }
    if tracked.dist.size:
        camera["D"] = tracked.dist.tolist()
    (out / "cameras.json").write_text(
        json.dumps({"fps": tracked.fps, "cameras": {CAMERA_NAME: camera}}, indent=2)
    )
    write_training_poses(out / "poses.npz", tracked, keep)
    flags = tracked.flags if tracked.flags is not None else np.array([""] * len(tracked))
    skipped = skip_reasons(tracked.confidence, flags, min_confidence)
    camera = json.loads(tracked.camera) if tracked.camera else None
    report = {
        "frames": len(keep),
        "kept": int(keep.sum()),
        "skipped": int((~keep).sum()),
        "skipped_by_reason": skipped,
        "min_confidence": min_confidence,
        "camera": camera,
        "camera_text": describe_camera(camera),
        "poses": str(poses_path),
    }
    (out / TRACKING_REPORT).write_text(json.dumps(report, indent=2) + "\n")
    why = ", ".join(f"{n} {reason}" for reason, n in sorted(skipped.items(), key=lambda kv: -kv[1]))
    log.info(
        "%s: %d of %d frames confident enough for training -> %s%s",
        source,
        keep.sum(),
        len(keep),
        out,
        f"; skipped {int((~keep).sum())}: {why}" if why else "",
    )
    if camera:
        log.info("%s", describe_camera(camera))
    return out
