"""Scoring a run against a synthetic subject's ground truth, whatever poses it trained on: the
subject's held-out cameras and held-out poses, over the whole image and per body part.

``stg-eval`` scores a run on its own dataset. A run trained on the video of a synthetic subject's
training camera (``stg-train --format video``: the tracker's poses and masks) lives in the
tracker's world instead: the training camera's frame, at the scale of the tracked body. To
compare it with a run trained on the ground-truth parameters, :func:`evaluate_on_synth` puts the
subject's held-out cameras into the run's world:

- rotation and position from the training camera's extrinsics (the tracker's world is that
  camera's frame, ``x_run = s (R1 x_world + t1)``);
- one scale ``s`` for the whole sequence: the median over training frames of the tracked body's
  depth over the true body's depth in the training camera. A single camera knows distances only
  up to the body's size (the tracker takes the size from its shape fit); this is the one gauge
  the evaluation fixes with the ground truth, once per sequence, never per frame.

Poses: novel views are training frames rendered with the run's own (refined) training poses;
novel poses are held-out frames rendered with the poses the tracker gave them, as tracked (a
live user has nothing better: no optimisation against the held-out image). A run trained on the
ground-truth parameters (``--format synthetic``) is scored the same way with the identity
alignment, so the two sets of figures compare directly.

``align="similarity"`` replaces the extrinsics and depth ratio by the one similarity (rotation,
translation, scale) that best maps all true joints of the training frames onto the tracked ones:
a tracked world may sit tilted or turned against the truth as a whole (a tracker's systematic
bias), which no live user would notice and a fair novel-view score should not charge. Still one
gauge per sequence, never per frame.

A diagnostic, never the score: ``root="true"`` moves each frame's tracked body so its pelvis sits
on the true pelvis (the tracked joint rotations and shape kept). A single camera knows a
person's distance only through the body's apparent size; a few centimetres of per-frame depth
error are invisible in the training view and shift the body sideways in a camera at 90 degrees.
The difference between the two scores says how much of a gap is where the body stands, and how
much is how it is posed and what the avatar learned. Per-part PSNR uses the true surface's
part labels (:mod:`stg_node.data.synth.body_parts`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stg_node.data.types import Camera

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class WorldAlignment:
    """Maps the subject's world into a run's world: ``x_run = scale * (R @ x_world + t)``."""

    R: np.ndarray
    t: np.ndarray
    scale: float

    @classmethod
    def identity(cls) -> WorldAlignment:
        return cls(np.eye(3), np.zeros(3), 1.0)

    def camera(self, camera: Camera) -> Camera:
        """``camera`` (world-to-camera in the subject's world) as a camera of the run's world.

        ``x_cam = Rk x_world + tk`` with ``x_world = R^T (x_run / s - t)`` gives
        ``x_cam = (Rk R^T) x_run / s + (tk - Rk R^T t)``; a pinhole image does not change when the
        camera-frame point is scaled, so ``x_run -> Rk R^T x_run + s (tk - Rk R^T t)`` sees the same."""
        rotation = np.asarray(camera.R, np.float64) @ self.R.T
        translation = self.scale * (np.asarray(camera.t, np.float64).reshape(3) - rotation @ self.t)
        return dataclasses.replace(camera, R=rotation, t=translation)


def tracked_alignment(
    train_camera: Camera, true_joints_world: np.ndarray, run_joints: np.ndarray
) -> WorldAlignment:
    """The alignment of a run trained in the training camera's frame: that camera's extrinsics and the
    median ratio of the run's body depth to the true body depth (joints (N, J, 3) of the same frames)."""
    R = np.asarray(train_camera.R, np.float64)
    t = np.asarray(train_camera.t, np.float64).reshape(3)
    true_depth = (np.asarray(true_joints_world) @ R.T + t)[..., 2].mean(axis=1)
    run_depth = np.asarray(run_joints)[..., 2].mean(axis=1)
    ok = true_depth > 1e-3
    if not ok.any():
        raise ValueError("no frame has the body in front of the training camera")
    return WorldAlignment(R, t, float(np.median(run_depth[ok] / true_depth[ok])))


def similarity_alignment(true_joints_world: np.ndarray, run_joints: np.ndarray) -> WorldAlignment:
    """The one similarity (rotation, translation, scale) for the whole sequence that best maps the
    true joints onto the run's (joints (N, J, 3) of the same frames, every joint of every frame
    pooled): the fairest single gauge for a tracked world, which may sit rotated and scaled
    against the truth beyond what the training camera's extrinsics say (a tracker's systematic
    tilt, its shape's size). Never per frame: a per-frame fit would hide the tracker's errors."""
    from stg_node.tracking.evaluation import similarity

    scale, rotation, translation = similarity(
        np.asarray(true_joints_world, np.float64).reshape(-1, 3),
        np.asarray(run_joints, np.float64).reshape(-1, 3),
    )
    if not scale > 0:
        raise ValueError("no similarity maps the true joints onto the run's (degenerate joints)")
    return WorldAlignment(rotation, translation / scale, scale)


def _joints(body, smpls) -> np.ndarray:
    from stg_node.tracking.evaluation import joints_from_params

    return joints_from_params(
        body,
        np.stack([np.asarray(s.poses, np.float32).reshape(72) for s in smpls]),
        np.stack([np.asarray(s.Rh, np.float32) for s in smpls]),
        np.stack([np.asarray(s.Th, np.float32) for s in smpls]),
        np.stack([np.asarray(s.betas, np.float32) for s in smpls]),
    )


def _tracker_world(folder: Path) -> bool:
    """Whether a folder dataset's cameras are a tracker's: one camera, at the origin, unrotated."""
    import json

    cameras = json.loads((folder / "cameras.json").read_text()).get("cameras", {})
    if len(cameras) != 1:
        return False
    (camera,) = cameras.values()
    return np.allclose(camera.get("R", 0), np.eye(3)) and np.allclose(camera.get("t", 1), 0)


def _run_poses(run, spec) -> dict:
    """Frame -> the pose the run has for it: a video run's every tracked frame, and so for a folder
    dataset in a tracker's world (one camera at the origin, as stg-track writes it: a tracking
    edited by hand, a diagnostic's substituted poses); empty for a dataset in the subject's world."""
    from stg_node.body.motion import load_smpl_params
    from stg_node.safe_load import load_npz

    if spec.format not in ("video", "folder"):
        return {}
    if spec.format == "folder" and not _tracker_world(Path(spec.root)):
        return {}
    path = Path(spec.root) / "poses.npz"
    sequence = load_smpl_params(path)
    frames = np.asarray(load_npz(path)["frames"]).astype(np.int64)
    return {int(f): sequence[i] for i, f in enumerate(frames)}


def _root_at_truth(body, smpl, true_smpl, alignment: WorldAlignment):
    """``smpl`` translated so its pelvis lands on ``true_smpl``'s pelvis (mapped into the run's world)."""
    pelvis = _joints(body, [smpl])[0, 0]
    true_pelvis = _joints(body, [true_smpl])[0, 0]
    target = alignment.scale * (alignment.R @ true_pelvis + alignment.t)
    shift = (target - pelvis).reshape(np.shape(smpl.Th))
    return dataclasses.replace(smpl, Th=(np.asarray(smpl.Th, np.float64) + shift).astype(np.float32))


#: ``swap`` diagnostics: which of the true parameters replace the tracked ones at render time.
SWAPS = ("none", "orientation", "pose")


def _swapped(smpl, true_smpl, alignment: WorldAlignment, swap: str):
    """``smpl`` with the true global orientation (mapped into the run's world) and, for ``pose``, the
    true joint rotations too; the tracked shape kept (the avatar is built on it)."""
    from stg_node.data.synth.rotations import axis_angle_to_matrix, matrix_to_axis_angle

    if swap == "none":
        return smpl
    true_R = axis_angle_to_matrix(np.asarray(true_smpl.Rh, np.float64).reshape(3))
    Rh = matrix_to_axis_angle(alignment.R @ true_R).reshape(np.shape(smpl.Rh)).astype(np.float32)
    poses = np.array(smpl.poses, np.float32)
    true_poses = np.asarray(true_smpl.poses, np.float32).reshape(poses.shape)
    if swap == "pose":
        poses = true_poses.copy()
    poses[0] = true_poses[0]  # the root joint's rotation is part of the orientation
    return dataclasses.replace(smpl, Rh=Rh, poses=poses)


def evaluate_on_synth(
    run_dir: str | Path,
    synth_dir: str | Path,
    split: str = "novel_view",
    *,
    root: str = "tracked",
    align: str = "camera",
    protocol: str = "full",
    lpips_nets: tuple[str, ...] = ("alex",),
    parts: bool = True,
    device="cpu",
    backend="auto",
    show_progress: bool = True,
    resample: float = 1.0,
    same_camera: bool = False,
    swap: str = "none",
) -> dict:
    """A run scored on an stg-synth subject's ``split`` (module docstring): PSNR / SSIM / LPIPS under
    ``protocol`` (``full``: the whole image, as stg-eval; ``bbox``: the person's box), PSNR per body
    part, the alignment used and the views that had no pose (a frame the tracker was unsure of).
    ``root``: ``tracked`` (the score) or ``true`` (the diagnostic of the module docstring).
    ``align`` (a tracked run): ``camera`` (the training camera's extrinsics and the depth-ratio
    scale) or ``similarity`` (:func:`similarity_alignment`). ``resample`` < 1: render, truth and mask
    shrunk by this factor (area average) before scoring, to score people filmed at different sizes
    at the same resolution of the person (tools/bench_footage.py size). ``same_camera`` (novel_pose
    only): every held-out frame of the training camera and no other camera, as ``stg-eval
    --split novel_pose`` scores a video run (the frames after the training range, same camera),
    in place of the benchmark's every 30th frame of every camera. ``swap`` (a tracked run, a
    diagnostic like ``root="true"``, never the score): ``orientation`` renders each frame with the
    true global orientation, ``pose`` with the true orientation and joint rotations (the tracked
    shape and, unless ``root="true"``, the tracked position kept; no learnt correction)."""
    from stg_node.avatar.data_spec import DataSpec
    from stg_node.avatar.loading import corrected, load_run_renderer
    from stg_node.body import load_body_model
    from stg_node.data.metrics import Evaluator
    from stg_node.data.synth.body_parts import PARTS, RegionScores, SynthPartLabeller
    from stg_node.progress import progress

    if split not in ("novel_view", "novel_pose"):
        raise ValueError(f"split must be novel_view or novel_pose, got {split!r}")
    if root not in ("tracked", "true"):
        raise ValueError(f"root must be tracked or true, got {root!r}")
    if align not in ("camera", "similarity"):
        raise ValueError(f"align must be camera or similarity, got {align!r}")
    if swap not in SWAPS:
        raise ValueError(f"swap must be one of {SWAPS}, got {swap!r}")
    if not 0.0 < resample <= 1.0:
        raise ValueError(f"resample must be in (0, 1], got {resample}")
    if same_camera and split != "novel_pose":
        raise ValueError("same_camera scores held-out frames: it needs split='novel_pose'")
    if resample != 1.0 and parts:
        raise ValueError("resample needs parts=False (the part labels are at the images' own size)")
    synth_dir = Path(synth_dir)
    run, renderer, corrections, summary = load_run_renderer(Path(run_dir), device=device, backend=backend)
    spec = run.data_spec()
    truth = DataSpec(str(synth_dir.resolve()), "synthetic", spec.train_frames, None, spec.size)
    train_truth = truth.open("train")
    tracked = _run_poses(run, spec)
    body = load_body_model()
    if tracked:  # the run's world is the training camera's, at the tracked body's scale
        frames = [f for f in train_truth.frames if f in tracked]
        if not frames:
            raise ValueError(f"{run.path}: none of its tracked frames is a training frame of {synth_dir}")
        true_joints = _joints(body, [train_truth.smpl(f) for f in frames])
        run_joints = _joints(body, [tracked[f] for f in frames])
        if align == "similarity":
            alignment = similarity_alignment(true_joints, run_joints)
        else:
            alignment = tracked_alignment(
                train_truth.camera(train_truth.camera_names[0]), true_joints, run_joints
            )
    else:
        alignment = WorldAlignment.identity()
    dataset = _held_out_same_camera(synth_dir, train_truth, spec.size) if same_camera else truth.open(split)
    evaluator = Evaluator(protocol, lpips_nets=lpips_nets)
    part_scores = RegionScores()
    labeller = SynthPartLabeller(synth_dir, body) if parts else None
    missing = 0
    for sample in progress(dataset, desc=f"eval {split}", unit="view", enabled=show_progress):
        if tracked:
            smpl = tracked.get(sample.index)
            if smpl is None:
                missing += 1
                continue
        else:
            smpl = sample.smpl
        if tracked and swap != "none":
            smpl = _swapped(smpl, sample.smpl, alignment, swap)
        elif split == "novel_view":
            smpl = corrected(smpl, corrections.get(sample.index))
        if tracked and root == "true":
            smpl = _root_at_truth(body, smpl, sample.smpl, alignment)
        time_s = sample.time if split == "novel_view" else None
        out = renderer.render(alignment.camera(sample.camera), smpl, time_s)
        target = np.where(sample.mask[..., None] > 127, sample.image, 0).astype(np.uint8)
        if resample != 1.0:
            evaluator.add(*_shrunk(resample, out.image, target, sample.mask))
        else:
            evaluator.add(out.image, target, sample.mask)
        if labeller is not None:
            part_scores.add(out.image, target, labeller.regions(sample.index, sample.camera))
    report = evaluator.report().as_dict()
    lpips = report["lpips"].get(lpips_nets[0], math.nan) if lpips_nets else math.nan
    return {
        "split": split,
        "root": root,
        "swap": swap if tracked else "none",
        "align": align if tracked else "identity",
        "protocol": protocol,
        "resample": resample,
        "format": spec.format,
        "psnr": report["psnr"],
        "ssim": report["ssim"],
        "lpips": lpips,
        "views": report["views"],
        "views_without_pose": missing,
        "parts_psnr": {name: part_scores.psnr(name) for name in PARTS} if parts else {},
        "alignment_scale": alignment.scale,
        "train_seconds": summary.get("train_seconds", math.nan),
        "gaussians": summary.get("gaussians"),
    }


def _held_out_same_camera(synth_dir: Path, train_truth, size):
    """Every frame after the generator's training range, seen by the (first) training camera."""
    from stg_node.data.splits import FrameRange, SplitSpec
    from stg_node.data.synth.dataset import open_synth
    from stg_node.data.synth.writer import read_metadata

    n_train = int(read_metadata(synth_dir)["num_train_frames"])
    spec = SplitSpec("novel_pose", FrameRange(n_train, None), cameras=(train_truth.camera_names[0],))
    return open_synth(synth_dir, spec, size=size)


def _shrunk(factor: float, image, target, mask):
    """``image``, ``target`` (H, W, 3) and ``mask`` (H, W) shrunk by ``factor`` (area average; the
    mask thresholded at half coverage)."""
    import cv2

    h, w = mask.shape[:2]
    size = (max(1, round(w * factor)), max(1, round(h * factor)))

    def shrink(a):
        a = np.asarray(a)
        a = a.astype(np.float32) / 255.0 if a.dtype == np.uint8 else a.astype(np.float32)
        return cv2.resize(a, size, interpolation=cv2.INTER_AREA)

    return shrink(image), shrink(target), (shrink(mask) >= 0.5).astype(np.uint8) * 255
