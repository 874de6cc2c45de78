"""Accuracy of the tracker against ground truth: 3D joint errors, keypoint errors, masks, jitter.

- :func:`mpjpe`: mean per-joint position error after aligning the root joints (the pelvis):
  the pose error without the global translation, which a monocular camera only knows up to the
  body's scale.
- :func:`pa_mpjpe`: the same after the best similarity transform (Procrustes: rotation,
  translation, scale) per frame: the articulation error alone.
- :func:`acceleration_error`: mean difference of the joints' second differences (jitter), m/frame^2.
- :func:`evaluate_synth`: the whole chain on a synthetic benchmark folder (stg-synth): its
  training camera's frames as a video file (or the image folder), through :func:`track_to_file`,
  against the SMPL joints of ``new_params`` in that camera's frame. tools/eval_track.py runs it.
"""

from __future__ import annotations

import dataclasses
import logging
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

log = logging.getLogger(__name__)


def _check_joints(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pred = np.asarray(pred, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if pred.shape != gt.shape or pred.ndim != 3 or pred.shape[2] != 3:
        raise ValueError(f"joints must both be (N, J, 3), got {pred.shape} and {gt.shape}")
    return pred, gt


def mpjpe(pred: np.ndarray, gt: np.ndarray, root: int = 0) -> np.ndarray:
    """(N,) mean joint distance per frame after subtracting each skeleton's ``root`` joint."""
    pred, gt = _check_joints(pred, gt)
    aligned = pred - pred[:, root : root + 1]
    return np.linalg.norm(aligned - (gt - gt[:, root : root + 1]), axis=-1).mean(axis=1)


def similarity(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(scale, rotation, translation) that best map ``source`` (P, 3) onto ``target`` (P, 3) in the
    least-squares sense: ``target ~ scale * rotation @ source + translation`` (Umeyama)."""
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    a, b = source - mu_s, target - mu_t
    u, s, vt = np.linalg.svd(a.T @ b)
    d = np.ones(3)
    d[2] = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rotation = vt.T @ np.diag(d) @ u.T
    variance = (a**2).sum()
    scale = (s * d).sum() / variance if variance > 0 else 1.0
    return float(scale), rotation, mu_t - scale * rotation @ mu_s


def procrustes_align(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``source`` (J, 3) moved by the similarity transform that best fits it to ``target`` (Umeyama)."""
    scale, rotation, translation = similarity(source, target)
    return scale * source @ rotation.T + translation


def pa_mpjpe(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """(N,) mean joint distance per frame after Procrustes alignment (rotation, translation, scale)."""
    pred, gt = _check_joints(pred, gt)
    aligned = np.stack([procrustes_align(p, g) for p, g in zip(pred, gt, strict=True)])
    return np.linalg.norm(aligned - gt, axis=-1).mean(axis=1)


def acceleration_error(pred: np.ndarray, gt: np.ndarray, root: int = 0) -> float:
    """Mean |second difference of pred - that of gt| over root-aligned joints (m/frame^2)."""
    pred, gt = _check_joints(pred, gt)
    if pred.shape[0] < 3:
        return float("nan")
    pred = pred - pred[:, root : root + 1]
    gt = gt - gt[:, root : root + 1]
    acc = lambda x: x[2:] - 2 * x[1:-1] + x[:-2]  # noqa: E731
    return float(np.linalg.norm(acc(pred) - acc(gt), axis=-1).mean())


def mask_iou(pred: np.ndarray, gt: np.ndarray) -> float:
    p, g = np.asarray(pred) > 0, np.asarray(gt) > 0
    union = (p | g).sum()
    return float((p & g).sum() / union) if union else 1.0


@dataclass
class EvalReport:
    frames: int
    mpjpe_mm: float  # mean over frames
    pa_mpjpe_mm: float
    median_mpjpe_mm: float
    accel_mm: float  # acceleration error, mm/frame^2
    mask_iou: float
    confident_fraction: float  # confidence >= 0.5
    seconds: float  # wall time of the tracking (decode + detect + fit + mask + write)
    per_frame_mpjpe_mm: list[float] = field(default_factory=list)

    @property
    def fps(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else float("nan")


def joints_from_params(body, poses, Rh, Th, betas, chunk: int = 64) -> np.ndarray:
    """(N, 24, 3) joints of the body model for per-frame SMPL parameters (float64 numpy)."""
    out = []
    with torch.no_grad():
        for lo in range(0, len(poses), chunk):
            hi = min(lo + chunk, len(poses))
            result = body(
                betas=torch.as_tensor(np.asarray(betas[lo:hi]), dtype=torch.float32),
                poses=torch.as_tensor(np.asarray(poses[lo:hi]).reshape(hi - lo, 72), dtype=torch.float32),
                Rh=torch.as_tensor(np.asarray(Rh[lo:hi]), dtype=torch.float32),
                Th=torch.as_tensor(np.asarray(Th[lo:hi]), dtype=torch.float32),
            )
            out.append(result.joints.double().numpy())
    return np.concatenate(out)


def write_video(frames: list[Path], out: Path, fps: float) -> Path:
    """Encode image files as a video (MJPG .avi, quality 95: what every OpenCV build writes)."""
    first = cv2.imread(str(frames[0]))
    if first is None:
        raise ValueError(f"cannot read {frames[0]}")
    height, width = first.shape[:2]
    writer = cv2.VideoWriter(str(out), cv2.VideoWriter_fourcc(*"MJPG"), fps, (width, height))
    if not writer.isOpened():
        raise OSError(f"OpenCV cannot write the video {out}")
    writer.set(cv2.VIDEOWRITER_PROP_QUALITY, 95)
    try:
        for path in frames:
            image = cv2.imread(str(path))
            if image is None or image.shape[:2] != (height, width):
                raise ValueError(f"cannot read {path} as a {width}x{height} image")
            writer.write(image)
    finally:
        writer.release()
    return out


def evaluate_synth(
    folder: str | Path,
    options=None,
    *,
    as_video: bool = True,
    work_dir: str | Path | None = None,
    progress: bool = True,
    threads: int | None = None,
) -> EvalReport:
    """Track the training camera of an stg-synth folder and compare with its ground truth."""
    import json

    from stg_node.body import load_body_model
    from stg_node.data.io import read_mask
    from stg_node.data.synth import read_metadata
    from stg_node.data.synth.cameras import camera_name
    from stg_node.safe_load import load_npy
    from stg_node.tracking.pipeline import TrackOptions, track_to_file
    from stg_node.tracking.poses_file import read_poses

    folder = Path(folder)
    metadata = read_metadata(folder)
    annots = load_npy(folder / "annots.npy")
    K = np.asarray(annots["cams"]["K"][0], dtype=np.float64)
    R = np.asarray(annots["cams"]["R"][0], dtype=np.float64)
    t = np.asarray(annots["cams"]["T"][0], dtype=np.float64).reshape(3) / 1000.0
    image_dir = folder / camera_name(0)
    frames = sorted(image_dir.glob("*.png"))
    if not frames:
        raise ValueError(f"{image_dir}: no frames")
    with tempfile.TemporaryDirectory(dir=work_dir) as tmp:
        tmp = Path(tmp)
        intrinsics = tmp / "K.json"
        intrinsics.write_text(json.dumps({"K": K.tolist()}))
        base = options or TrackOptions()
        options = dataclasses.replace(base, intrinsics=str(intrinsics), fps=float(metadata["fps"]))
        source = write_video(frames, tmp / "input.avi", float(metadata["fps"])) if as_video else image_dir
        summary = track_to_file(
            source, tmp / "POSES.npz", options, masks_dir=tmp / "masks", progress=progress, threads=threads
        )
        tracked = read_poses(tmp / "POSES.npz")
        ious = [
            mask_iou(
                cv2.imread(str(tmp / "masks" / f"{i:06d}.png"), 0),
                read_mask(folder / "mask" / p.relative_to(folder)),
            )
            for i, p in enumerate(frames)
        ]
    # Ground truth on the body that rendered the benchmark (the open body); the prediction on the
    # body the tracker fitted.
    truth_body = load_body_model()
    body = load_body_model(options.smpl_model)
    params = [load_npy(folder / "new_params" / f"{int(p.stem)}.npy") for p in frames]
    gt_world = joints_from_params(
        truth_body,
        np.concatenate([p["poses"] for p in params]),
        np.concatenate([p["Rh"] for p in params]),
        np.concatenate([p["Th"] for p in params]),
        np.concatenate([p["shapes"] for p in params]),
    )
    gt = gt_world @ R.T + t
    pred = joints_from_params(body, tracked.poses, tracked.Rh, tracked.Th, tracked.shapes)
    if len(pred) != len(gt):
        raise ValueError(f"tracked {len(pred)} frames but the benchmark has {len(gt)}")
    per_frame = mpjpe(pred, gt) * 1000
    return EvalReport(
        frames=len(gt),
        mpjpe_mm=float(per_frame.mean()),
        pa_mpjpe_mm=float(pa_mpjpe(pred, gt).mean() * 1000),
        median_mpjpe_mm=float(np.median(per_frame)),
        accel_mm=acceleration_error(pred, gt) * 1000,
        mask_iou=float(np.mean(ious)),
        confident_fraction=float((tracked.confidence >= 0.5).mean()),
        seconds=summary.seconds,
        per_frame_mpjpe_mm=per_frame.round(1).tolist(),
    )
