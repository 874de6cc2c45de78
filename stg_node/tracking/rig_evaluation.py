"""Accuracy of multi-view tracking against ground truth: a synthetic rig, its videos, SMPL joints out.

:func:`evaluate_synth_rig` takes an stg-synth folder whose chosen cameras render every frame
(``stg-synth --train-cameras``), writes their calibration as a rig.json and their frames as one
video each, runs the rig pipeline (``stg-track CAM1 CAM2 ... --calibration rig.json``) and
compares the tracked SMPL joints with the true ones, in the world frame: MPJPE after aligning the
pelvis (as the monocular figure, evaluation.py), PA-MPJPE, and the pelvis's own position error
(a rig knows where the person is; one camera does not). tools/eval_track.py ``--rig N`` runs it.
"""

from __future__ import annotations

import dataclasses
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np


@dataclass
class RigEvalReport:
    frames: int
    cameras: list[str]
    mpjpe_mm: float  # pelvis-aligned, mean over frames
    pa_mpjpe_mm: float
    median_mpjpe_mm: float
    pelvis_mm: float  # mean distance of the pelvis joint from the truth (no alignment)
    accel_mm: float
    mask_iou: float  # mean over views and frames
    confident_fraction: float
    seconds: float
    per_frame_mpjpe_mm: list[float] = field(default_factory=list)

    @property
    def fps(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else float("nan")


def synth_rig(folder: Path, cameras: list[str]):
    """The rig of an stg-synth folder's cameras (``"1"`` = Camera_B1), as in its annots.npy."""
    from stg_node.calibration.rig import Rig, RigCamera
    from stg_node.safe_load import load_npy

    annots = load_npy(Path(folder) / "annots.npy")
    cams = annots["cams"]
    out = []
    for name in cameras:
        k = int(name) - 1
        first = cv2.imread(str(Path(folder) / f"Camera_B{name}" / "000000.png"))
        if first is None:
            raise ValueError(f"{folder}: camera {name} has no frame 000000.png")
        out.append(
            RigCamera(
                name,
                np.asarray(cams["K"][k], np.float64),
                np.asarray(cams["D"][k], np.float64).reshape(-1),
                np.asarray(cams["R"][k], np.float64),
                np.asarray(cams["T"][k], np.float64).reshape(3) / 1000.0,
                (first.shape[1], first.shape[0]),
            )
        )
    return Rig(tuple(out))


def evaluate_synth_rig(
    folder: str | Path,
    cameras: list[str],
    options=None,
    *,
    work_dir: str | Path | None = None,
    progress: bool = True,
    threads: int | None = None,
) -> RigEvalReport:
    """Track ``cameras`` of an stg-synth folder as a rig (MJPG videos) and compare with its truth."""
    from stg_node.body import load_body_model
    from stg_node.calibration.rig import write_rig
    from stg_node.data.io import read_mask
    from stg_node.data.synth import read_metadata
    from stg_node.safe_load import load_npy
    from stg_node.tracking.evaluation import (
        acceleration_error,
        joints_from_params,
        mask_iou,
        mpjpe,
        pa_mpjpe,
        write_video,
    )
    from stg_node.tracking.pipeline import TrackOptions
    from stg_node.tracking.poses_file import read_poses
    from stg_node.tracking.rig_pipeline import track_rig_to_file

    folder = Path(folder)
    metadata = read_metadata(folder)
    count = int(metadata["num_frames"])
    for name in cameras:
        rendered = metadata["rendered"].get(f"Camera_B{name}", [])
        if len(rendered) != count:
            raise ValueError(
                f"{folder}: camera {name} is rendered on {len(rendered)} of {count} frames; generate the "
                f"subject with stg-synth --train-cameras {','.join(cameras)}"
            )
    fps = float(metadata["fps"])
    rig = synth_rig(folder, cameras)
    with tempfile.TemporaryDirectory(dir=work_dir) as tmp:
        tmp = Path(tmp)
        rig_path = write_rig(tmp / "rig.json", rig)
        videos = [
            write_video(sorted((folder / f"Camera_B{name}").glob("*.png")), tmp / f"{name}.avi", fps)
            for name in cameras
        ]
        options = dataclasses.replace(options or TrackOptions(), fps=fps)
        summary = track_rig_to_file(
            videos,
            rig_path,
            tmp / "POSES.npz",
            options,
            masks_dir=tmp / "masks",
            progress=progress,
            threads=threads,
        )
        tracked = read_poses(tmp / "POSES.npz")
        ious = [
            mask_iou(
                cv2.imread(str(tmp / "masks" / name / f"{row:06d}.png"), 0),
                read_mask(
                    folder / "mask" / f"Camera_B{name}" / f"{int(tracked.camera_frames[row, v]):06d}.png"
                ),
            )
            for row in range(len(tracked))
            for v, name in enumerate(cameras)
        ]
    frames = tracked.camera_frames[:, 0]
    params = [load_npy(folder / "new_params" / f"{int(i)}.npy") for i in frames]
    truth_body = load_body_model()
    body = load_body_model(options.smpl_model)
    gt = joints_from_params(
        truth_body,
        np.concatenate([p["poses"] for p in params]),
        np.concatenate([p["Rh"] for p in params]),
        np.concatenate([p["Th"] for p in params]),
        np.concatenate([p["shapes"] for p in params]),
    )
    pred = joints_from_params(body, tracked.poses, tracked.Rh, tracked.Th, tracked.shapes)
    per_frame = mpjpe(pred, gt) * 1000
    return RigEvalReport(
        frames=len(gt),
        cameras=list(cameras),
        mpjpe_mm=float(per_frame.mean()),
        pa_mpjpe_mm=float(pa_mpjpe(pred, gt).mean() * 1000),
        median_mpjpe_mm=float(np.median(per_frame)),
        pelvis_mm=float(np.linalg.norm(pred[:, 0] - gt[:, 0], axis=-1).mean() * 1000),
        accel_mm=acceleration_error(pred, gt) * 1000,
        mask_iou=float(np.mean(ious)),
        confident_fraction=float((tracked.confidence >= 0.5).mean()),
        seconds=summary.seconds,
        per_frame_mpjpe_mm=per_frame.round(1).tolist(),
    )
