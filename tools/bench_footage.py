#!/usr/bin/env python3
"""Real footage, measured on the synthetic benchmark: what tracked poses, exposure drift, the person's
size in the frame and an unknown camera cost, and what each remedy buys back.

    python tools/bench_footage.py gap       [--size 512] [--frames 125] [--runs truth,...]  # tracked vs truth
    python tools/bench_footage.py sources   [--train-size 256] [...]      # where the gap comes from
    python tools/bench_footage.py exposure  [...]                         # steady vs exposure/WB jitter
    python tools/bench_footage.py size      [--close-m 1.9] [--far-m 5] [--figure PNG]  # close vs afar
    python tools/bench_footage.py focal     [...]                         # focal estimate vs truth, 30-90 deg
    python tools/bench_footage.py fit       [--size 256] [--frames 60]    # tracking, silhouette off/on
    python tools/bench_footage.py framing RUN_DIR [...]                   # how stg-render frames a run
    python tools/bench_footage.py refine    [--size 256] [--runs ...]     # the pose refinement's variants
    python tools/bench_footage.py chains    [--size 256] [--runs ...]     # the gap: torso chain vs limbs
    python tools/bench_footage.py errors    [--size 256]                  # what the tracked poses' errors are
    python tools/bench_footage.py twist     [--size 256] [--runs mixed,...] # tracker per bone, motions
    python tools/bench_footage.py closeup   [--size 256] [--frames 90] [--closeup-m 2.2] # same camera
    python tools/bench_footage.py cues      [--size 256] [--runs gap|closeup] # limbs' depth: fit vs 3D
    python tools/bench_footage.py twopass   [--size 256] [--runs gap|closeup] # the fit forwards + backwards
    python tools/bench_footage.py order     [--size 256] [--runs gap|closeup] # depth order: oracle, vote
    python tools/bench_footage.py ordertest [--size 256] [--runs gap|closeup] # the fit's depth-order test
    common: --out DIR (default runs/bench_footage) --preset fast --seed 0 --json

Every experiment generates its subjects with ``stg-synth``'s generator into ``--out/data``
(deterministic, seed 0), trains with ``stg-train`` (in-process, the same command users run) into
``--out/runs/NAME`` and scores novel views on the subject's held-out cameras with
:func:`stg_node.avatar.synth_eval.evaluate_on_synth` (a tracked run's world aligned to the
subject's by the training camera and one scale for the whole sequence; per body part). Results go
to ``--out/results/EXPERIMENT.json``; a run folder that is already finished is not trained again.

- ``gap``: the mixed subject (the README's benchmark). ``truth``: ``--format synthetic`` (the
  ground-truth SMPL parameters). ``tracked-before``: the camera-1 frames through ``--format video``
  with the training camera's intrinsics (our tracker's poses and masks) and the pose settings
  that were the default before (``lr_pose=1e-4``, no smoothness, no colour correction).
  ``tracked``: the same with today's defaults for tracked poses (avatar/pose_refine.py). Novel
  views and novel poses, overall and per body part; the novel poses of a tracked run use the
  tracker's poses as tracked. Beside it (``true_root``, a diagnostic, never the score): the tracked
  bodies moved so their pelvis sits on the true one, which separates where the body stands (a
  single camera's depth) from how it is posed and what the avatar learned.
- ``sources``: where the ``gap`` comes from. The training camera is tracked once
  (``stg-train --format video``'s own preparation) and its folder dataset (the tracker's images,
  masks, camera) is trained with the poses swapped: ``tracked``; ``true-orientation`` (the true
  global orientation, the tracked joint rotations, shape and pelvis position); ``true`` (the
  true parameters in the camera's frame), with the refinement for tracked poses and, as
  ``true, light refinement``, the one for given poses; beside ``truth`` (``--format
  synthetic``). True poses through the tracker's pipeline score what the pipeline costs; the
  steps between say what the pose errors cost. Scored with both alignments.
- ``exposure``: the mixed subject steady, and with ``--exposure-jitter 0.15`` trained with the
  per-frame colour correction as ``--format video`` trains (``lr_exposure`` 0.5) and without it
  (``lr_exposure=0``, the synthetic format's default); ``--runs`` any of
  steady,jitter,nocorr,steady-nocorr (default all). Beside each score: how well the learnt
  per-frame gains found the subject's true ones (RMS log-gain error, slope on the truth). The
  held-out cameras are rendered without jitter at the subject's true colour, and the jitter's
  log-gains average zero over the training frames, so the avatar is scored as rendered, with no
  colour fitted to a held-out image.
- ``size``: the turning subject (same body, texture, motion and held-out cameras) filmed by a
  55 degree camera from ``--close-m`` 1.9 m (the person fills the frame) and from ``--far-m`` 5.0
  m (a third of its height), ground-truth poses. The close one three ways: with the preset's
  budget (every setting budget.py scales held at the preset's value with ``--set``), with only
  the Gaussians and steps scaled (the pixel settings held), and with the whole scaled budget;
  ``--runs`` any of far,close-fixed,close-gs,close (default all; each row is kept in
  ``results/size_rows`` so processes running different ones share ``--out``). Novel views on
  the ``bbox`` protocol (the person's box, at each subject's own resolution, so a small
  person's black surround does not inflate the score), ``bbox_at_far_size`` (render, truth and
  mask shrunk, area-averaged, by the ratio of the far to the close person's median height: both
  people scored at the same resolution of the person) and ``full``. The scaling engages from
  about ``--size`` 420 (below it the close person covers fewer pixels than the presets'
  reference and every close row trains alike); the issue's figures are at 512.
- ``focal``: the ``approach`` motion (walks 2 m towards the camera and back) filmed at 30, 50,
  70 and 90 degrees (from 6, 4, 3 and 2.5 m), and the ``still`` motion at 60 degrees; stg-track's
  estimate against the truth and its verdict.
- ``fit``: the tracker's accuracy against the subject's truth, with the fit's silhouette term
  off (``silhouette_weight=0``, the fit before it) and on (the default), in the same process:
  the mixed subject's training camera through the Tracker (stg-track's per-frame path, the true
  intrinsics); MPJPE / PA-MPJPE, the error of every joint's rotation and of the global
  orientation (camera frame; mean, median, the worst joints), and the share of the full mesh's
  vertices projecting inside the tracker's own mask and inside the true mask (the true mesh: the
  ceiling). Each pass's poses go to ``--out/fit/NAME/poses.npz``. ``--runs`` adds training
  runs (``truth``; ``silhouette``: stg-train --format video's own preparation; ``keypoints`` and
  ``unsmoothed``: that folder with the keypoint-only or unsmoothed silhouette poses), scored on
  novel views.
- ``refine``: the tracked-pose gap and each pose-refinement variant (``REFINE_VARIANTS``: the
  settings for tracked poses plus a ``--set``; poses first, a stronger silhouette, more
  smoothness, the non-rigid part forced on) trained on the training camera's tracked folder,
  beside ``truth``; novel views (training frames, held-out cameras, each run's refined training
  poses), novel poses (held-out frames, the tracker's poses as tracked) per body part, and the
  refined training poses' error against the truth beside the tracked ones'.
- ``chains``: the same folder with the true torso chain (orientation, position, shape, spine,
  neck, collars, head) or the true limbs swapped in, the limbs' local rotations kept or their
  orientation in the camera's frame: which part of the body the gap sits in (a diagnostic).
- ``errors``: the tracked poses' bones against the truth in the camera's frame, the twist about
  each bone, and what a zero-lag smoothing in time would change.
- ``twist``: the tracker alone on several motions (``--runs``: ``stg-synth`` motions, default
  mixed, dance, wave, reach, walk), tracked as ``stg-train --format video`` tracks: MPJPE /
  PA-MPJPE, the global orientation's error, and each bone's (upper arms, forearms, hands,
  thighs, shins, feet, chest, neck) orientation error in the camera's frame with its twist.
- ``closeup``: what ``stg-eval RUN --split novel_pose`` scores on a real clip (the frames after the
  training range, the same camera, the tracker's poses as tracked), on a subject shaped like a
  martial-arts clip: the ``dance`` motion (fast, large arm and leg swings), the striped shirt and
  checked trousers, filling the frame (``--closeup-m`` 2.2 m from a 55 degree camera), facing the
  camera within a 90 degree window. ``tracked``: ``--format video`` on the training camera with
  its intrinsics, frames 0 to 0.8 N; ``truth``: ``--format synthetic``, same frames;
  ``true-poses``: the tracked run's own images, masks and camera with the true parameters (what
  the pipeline costs without pose errors). Scored on every held-out frame of the training camera
  against the true image and mask (``same_camera``), and on novel views, per body part; the gap
  to ``truth`` per part.
- ``decompose``: where the tracked run's gap goes (``--runs`` gap, closeup; default gap), with
  no new training: the tracked avatar rendered with the one similarity for the sequence, then
  each frame's pelvis at the true one, the true global orientation, the true joint rotations;
  what each step gains, per body part, and what the truth run still scores above the last (the
  avatar learnt on the tracked poses). Trains the ``gap``/``closeup`` runs it needs if missing.
  ``--runs gap-trained`` / ``closeup-trained``: the same question answered by training (an
  avatar learnt on tracked poses drawn with others is a confounded witness): the tracked run's
  own folder trained as ``--format video`` trains with the tracked poses, each frame at the true
  depth along its pelvis's ray, the true global orientation, the true parameters (``--steps``
  picks), scored as ``gap`` / ``closeup`` score, with the gap to the truth run per part; the
  steps ``true-arms``, ``true-legs``, ``true-torso`` turn one chain to its true orientation in
  the camera's frame and keep the rest as tracked (which chain's rotations carry the gap);
  ``twopass``: the training frames' poses from ``twopass``'s average (run it first);
  ``order-oracle`` / ``order-voted`` / ``order-test`` / ``retracked``: the folders ``order`` and
  ``ordertest`` write (run them first); ``toward-N`` / ``toward-joints-N`` / ``toward-body-N``:
  every parameter, the joints alone, or the body's turn, position and shape alone N % of the way
  from the tracked to the true (N in 50, 75, 90: how the score grows as the error shrinks).
  ``--set KEY=VALUE --variant NAME``: every step trained with that trainer setting, into runs
  named after the variant (a lever, measured with the same decomposition).
- ``cues``: the limbs' depth evidence on ``decompose``'s tracked folder (``--runs`` gap or
  closeup): per limb bone, the fit's and BlazePose's metric 3D points' direction, elevation and
  depth order against the truth; the fitted shape's bone lengths; each joint's error and twist.
- ``twopass``: the training frames tracked forwards, then backwards with the shape held, and the
  two fits averaged (a fixed-interval smoother against the temporal term's lag); joint errors.
- ``order``: each limb bone's depth order (which end is nearer the camera) on ``decompose``'s
  tracked folder: as tracked, set by the truth (a bound) and voted by BlazePose's 3D points over
  each run of one order; directions and joint errors, and the two folders for ``decompose``.
- ``ordertest``: the subject's camera tracked again with the fit's depth-order test
  (``FitConfig.order_test_bones``: upper arms and thighs; ``--variant limbs`` adds forearms and
  shins) and without; the same errors, and the folders ``order-test`` and ``retracked``.
- ``framing``: renders RUN_DIR's default orbit (and follow camera) and reports the share of
  frames with the avatar whole and at least 30 % of the image tall.

Exit codes: 0 done, 1 failed, 2 bad usage.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import platform
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from stg_node.avatar.exposure import FOOTAGE_RATE  # noqa: E402

log = logging.getLogger("bench_footage")


def machine() -> dict:
    import os

    return {
        "python": platform.python_version(),
        "cpu": platform.processor() or platform.machine(),
        "cores": os.cpu_count(),
        "load_1min": round(os.getloadavg()[0], 1),
        "threads": os.environ.get("STG_THREADS", "1"),
    }


def subject(out: Path, name: str, **config) -> Path:
    """An stg-synth subject in ``out/data/name`` (generated once)."""
    from stg_node.data.synth import SynthConfig, generate

    folder = out / "data" / name
    if (folder / "synth.json").is_file():
        return folder
    generate(SynthConfig(out=folder, overwrite=True, **config), progress=False)
    return folder


def intrinsics_file(folder: Path) -> Path:
    """The training camera's K as stg-track's --intrinsics JSON."""
    from stg_node.safe_load import load_npy

    path = folder / "camera_K.json"
    if not path.is_file():
        K = load_npy(folder / "annots.npy")["cams"]["K"][0]
        path.write_text(json.dumps({"K": [list(map(float, row)) for row in K]}))
    return path


def train(out: Path, name: str, args, *extra: str) -> Path:
    """``stg-train`` in-process into ``out/runs/name`` unless it already finished there."""
    from stg_node.cli import train as train_cli

    run = out / "runs" / name
    summary = run / "summary.json"
    if summary.is_file() and json.loads(summary.read_text()).get("finished"):
        return run
    argv = ["--out", str(run), "--preset", args.preset, "--seed", str(args.seed), "--no-progress", *extra]
    if args.iters is not None:  # smoke tests only: the figures are for the preset's own schedule
        argv += ["--iters", str(args.iters)]
    log.info("stg-train %s", " ".join(argv))
    code = train_cli.main(argv)
    if code != 0:
        raise RuntimeError(f"stg-train {' '.join(argv)} failed with exit code {code}")
    return run


def score(run: Path, data: Path, split: str = "novel_view", **kw) -> dict:
    from stg_node.avatar.synth_eval import evaluate_on_synth

    result = evaluate_on_synth(run, data, split, show_progress=False, **kw)
    summary = json.loads((run / "summary.json").read_text())
    result["train_seconds"] = summary.get("train_seconds")
    result["gaussians"] = summary.get("gaussians")
    result["budget"] = summary.get("budget")
    return result


def wanted_runs(runs: str | None, known, experiment: str) -> list[str]:
    """The runs ``--runs`` names (all of ``known`` without it); an unknown name is an error listing them."""
    known = list(known)
    wanted = runs.split(",") if runs else known
    unknown = sorted(set(wanted) - set(known))
    if unknown:
        raise ValueError(f"{experiment} --runs: unknown {unknown}; choose from {', '.join(known)}")
    return wanted


def camera_video_args(data: Path) -> list[str]:
    """stg-train arguments that train from the subject's camera-1 video through the tracker, with
    the camera's true intrinsics (the focal estimate is measured on its own, `focal`)."""
    intrinsics = str(intrinsics_file(data))
    return ["--data", str(data / "Camera_B1"), "--format", "video", "--intrinsics", intrinsics]


# --- experiments ---------------------------------------------------------------------------------
def gap(args) -> dict:
    out = args.out
    data = subject(out, f"mixed_{args.size}", num_frames=args.frames, size=args.size)
    video = camera_video_args(data)
    video += ["--train-frames", f"0:{round(0.8 * args.frames)}", "--size", str(args.size)]
    before = ["--set", "lr_pose=0.0001", "--set", "loss.pose_refine=0.001", "--set", "loss.pose_smooth=0.0",
              "--set", "lr_exposure=0.0"]  # fmt: skip
    flags = {
        "truth": ("--data", str(data), "--format", "synthetic", "--size", str(args.size)),
        "tracked-before": (*video, *before),
        "tracked": video,
    }
    wanted = wanted_runs(args.runs, flags, "gap")
    rows = {}
    for name in wanted:
        run = train(out, f"gap_{name.replace('-', '_')}_{args.size}", args, *flags[name])
        rows[name] = {split: score(run, data, split) for split in ("novel_view", "novel_pose")}
        if name != "truth":  # the diagnostic: the tracked bodies placed at the true pelvis
            rows[name]["true_root"] = {
                split: score(run, data, split, root="true", parts=False)
                for split in ("novel_view", "novel_pose")
            }
        cached = out / "results" / f"gap_{name}_{args.size}.json"  # for runs scored by another process
        cached.parent.mkdir(parents=True, exist_ok=True)
        cached.write_text(json.dumps(rows[name], default=float) + "\n")
    for name in flags:  # rows another process scored (--runs split across processes)
        cached = out / "results" / f"gap_{name}_{args.size}.json"
        if name not in rows and cached.is_file():
            rows[name] = json.loads(cached.read_text())
    for name in ("tracked-before", "tracked"):
        if name in rows and "truth" in rows:
            rows[name]["gap_db"] = {
                split: rows["truth"][split]["psnr"] - rows[name][split]["psnr"]
                for split in ("novel_view", "novel_pose")
            }
    return rows


def pose_variants(video_data: Path, data: Path, out: Path) -> dict[str, Path]:
    """Folder datasets in the tracker's world (its images, masks and camera) with the poses swapped:
    ``tracked`` as tracked; ``true-orientation``: the tracked joint rotations, shape and pelvis
    position with the true global orientation; ``true``: the true parameters (pose, shape,
    orientation, position) in the training camera's frame; ``true-depth``: the tracked parameters
    with each frame's body slid along the camera ray through its pelvis to the true pelvis depth
    (times the sequence's one depth-ratio scale, the gauge the scoring fixes): the picture in
    the training camera unchanged at the pelvis, the single camera's depth error gone;
    ``true-arms`` / ``true-legs`` / ``true-torso``: one chain turned true in the camera's frame
    (:func:`chain_true_in_world`); ``toward-N``: every parameter N % of the way from the tracked to
    the true (:func:`toward_truth`), ``toward-joints-N`` the local joint rotations alone,
    ``toward-body-N`` the global orientation, position and shape alone. Each is ``out/NAME``."""
    import dataclasses

    import numpy as np

    from stg_node.avatar.data_spec import DataSpec
    from stg_node.avatar.synth_eval import _joints, tracked_alignment
    from stg_node.body import load_body_model
    from stg_node.body.motion import load_smpl_params
    from stg_node.safe_load import load_npz

    tracked = {k: np.asarray(v) for k, v in load_npz(video_data / "poses.npz").items()}
    sequence = load_smpl_params(video_data / "poses.npz")
    truth = DataSpec(str(data.resolve()), "synthetic", None, None, None).open("train")
    camera = truth.camera(truth.camera_names[0])
    R1, t1 = np.asarray(camera.R, np.float64), np.asarray(camera.t, np.float64).reshape(3)
    body = load_body_model()
    variants = {
        name: {k: v.copy() for k, v in tracked.items()}
        for name in ("tracked", "true-orientation", "true", "true-depth")
    }
    frames = tracked["frames"].astype(int)
    tracked_joints = _joints(body, [sequence[i] for i in range(len(sequence))])
    true_sequence = _joints(body, [truth.smpl(int(f)) for f in frames])
    gauge = tracked_alignment(camera, true_sequence, tracked_joints).scale  # the scoring's depth ratio
    for i, frame in enumerate(tracked["frames"].astype(int)):
        true = truth.smpl(int(frame))
        poses, Rh, Th = in_camera_frame(body, true, R1, t1)
        true_joints = _joints(body, [true])[0] @ R1.T + t1
        row = variants["true"]
        row["poses"][i], row["Rh"][i], row["shapes"][i] = poses, Rh, np.asarray(true.betas)[:10]
        row["Th"][i] = Th
        mine = sequence[i]
        turned = dataclasses.replace(mine, Rh=Rh.astype(np.float32), Th=np.zeros(3, np.float32))
        row = variants["true-orientation"]
        row["Rh"][i] = Rh
        row["Th"][i] = _joints(body, [mine])[0, 0] - _joints(body, [turned])[0, 0]  # the tracked pelvis kept
        pelvis = tracked_joints[i, 0]
        variants["true-depth"]["Th"][i] = slid_to_depth(mine.Th, pelvis, gauge * true_joints[0, 2])
    true_rows = variants["true"]
    for name, chain in CHAINS.items():
        variants[f"true-{name}"] = chain_true_in_world(variants["tracked"], true_rows, chain)
    for percent in TOWARD_TRUTH_PERCENT:
        variants[f"toward-{percent}"] = toward_truth(variants["tracked"], true_rows, percent / 100.0)
        for which in ("joints", "body"):
            variants[f"toward-{which}-{percent}"] = toward_truth(
                variants["tracked"], true_rows, percent / 100.0, which=which
            )
    return {name: write_pose_variant(out / name, video_data, rows) for name, rows in variants.items()}


def in_camera_frame(body, smpl, R, t) -> tuple:
    """``smpl`` (world frame) in the frame of the camera ``X_cam = R X + t``, as the tracker writes
    its rows: (poses (72,) with the root rotation folded into ``Rh``, ``Rh`` (3,), ``Th`` (3,))."""
    import dataclasses

    import cv2
    import numpy as np

    from stg_node.avatar.synth_eval import _joints

    poses = np.asarray(smpl.poses, np.float64).reshape(24, 3).copy()
    rotation = R @ cv2.Rodrigues(np.asarray(smpl.Rh, np.float64).reshape(3))[0] @ cv2.Rodrigues(poses[0])[0]
    Rh = cv2.Rodrigues(rotation)[0].ravel()
    poses[0] = 0.0  # the root rotation folded into Rh, as the tracker writes it
    placed = dataclasses.replace(smpl, poses=poses.astype(np.float32), Rh=Rh.astype(np.float32),
                                 Th=np.zeros(3, np.float32))  # fmt: skip
    joints = _joints(body, [smpl])[0] @ np.asarray(R).T + np.asarray(t).reshape(3)
    return poses.reshape(72), Rh, (joints - _joints(body, [placed])[0]).mean(axis=0)  # a translation: exact


RIG_CAMERAS = ("1", "7", "13", "18")  # eval_track --rig 4's of the 23-camera ring: 0, 94, 188, 266 deg


def rig_folder(args, data: Path, tracked: Path) -> Path:
    """``tracked`` (a ``pose_variants`` folder: camera 1's images, masks and camera) with its poses
    from the multi-view tracker (``stg_node.tracking.rig_pipeline``) run on the same subject (seed,
    motion, frames, size) filmed by :data:`RIG_CAMERAS` as MJPG videos, its world-frame fit put in
    camera 1's frame: what training gains from a rig's tracking, nothing else changed. The folder
    ``rig`` beside ``tracked``; the rig's subject ``data/NAME_rig4``, its fit ``rig_poses.npz``."""
    import dataclasses
    import tempfile

    import cv2
    import numpy as np

    from stg_node.avatar.data_spec import DataSpec
    from stg_node.body import load_body_model
    from stg_node.body.motion import load_smpl_params
    from stg_node.calibration.rig import write_rig
    from stg_node.data.synth import read_metadata
    from stg_node.safe_load import load_npz
    from stg_node.tracking.evaluation import write_video
    from stg_node.tracking.pipeline import TrackOptions
    from stg_node.tracking.rig_evaluation import synth_rig
    from stg_node.tracking.rig_pipeline import track_rig_to_file

    meta = read_metadata(data)
    count = int(meta["num_frames"])
    rig_data = subject(args.out, f"{data.name}_rig4", seed=int(meta["seed"]), motion=meta["motion"],
                       num_frames=count, size=int(meta["size"][0]), num_novel_views=22, view_every=count,
                       train_cameras=tuple(int(c) - 1 for c in RIG_CAMERAS))  # fmt: skip
    first = [sorted((folder / "Camera_B1").glob("*.png")) for folder in (data, rig_data)]
    for mine, theirs in zip(*first, strict=True):
        if not np.array_equal(cv2.imread(str(mine)), cv2.imread(str(theirs))):
            raise ValueError(f"{rig_data}: camera 1 does not render {data}'s images ({theirs.name})")
    fit = tracked.parent / "rig_poses.npz"
    if not fit.is_file():
        with tempfile.TemporaryDirectory() as tmp:
            tmp = Path(tmp)
            fps = float(meta["fps"])
            rig_path = write_rig(tmp / "rig.json", synth_rig(rig_data, list(RIG_CAMERAS)))
            videos = [write_video(sorted((rig_data / f"Camera_B{n}").glob("*.png")), tmp / f"{n}.avi", fps)
                      for n in RIG_CAMERAS]  # fmt: skip
            options = dataclasses.replace(TrackOptions(), fps=fps)
            track_rig_to_file(videos, rig_path, fit, options, progress=False)
    rows = {k: np.asarray(v).copy() for k, v in load_npz(tracked / "poses.npz").items()}
    sequence = load_smpl_params(fit)
    truth = DataSpec(str(data.resolve()), "synthetic", None, None, None).open("train")
    camera = truth.camera(truth.camera_names[0])
    R1, t1 = np.asarray(camera.R, np.float64), np.asarray(camera.t, np.float64).reshape(3)
    body = load_body_model()
    for i, frame in enumerate(rows["frames"].astype(int)):
        mine = sequence[int(frame)]
        rows["poses"][i], rows["Rh"][i], rows["Th"][i] = in_camera_frame(body, mine, R1, t1)
        rows["shapes"][i] = np.asarray(mine.betas)[:10]
    return write_pose_variant(tracked.parent / "rig", tracked, rows)


def write_pose_variant(folder: Path, source: Path, rows: dict) -> Path:
    """A training folder that is ``source`` (a ``--format video`` data folder) with its poses
    replaced by ``rows`` (poses.npz columns): images and masks linked, the cameras copied."""
    import os
    import shutil

    import numpy as np

    folder.mkdir(parents=True, exist_ok=True)
    for sub in ("images", "masks"):
        if not (folder / sub).exists():
            os.symlink((source / sub).resolve(), folder / sub)
    shutil.copy(source / "cameras.json", folder / "cameras.json")
    np.savez(folder / "poses.npz", **rows)
    return folder


CHAINS = {  # the joints (SMPL indices) whose orientation in the camera's frame a chain step makes true
    "arms": (16, 17, 18, 19, 20, 21, 22, 23),  # shoulders, elbows, wrists, hands
    "legs": (1, 2, 4, 5, 7, 8, 10, 11),  # hips, knees, ankles, feet
    "torso": (3, 6, 9, 12, 13, 14, 15),  # spine, neck, collars, head
}


def joint_world_rotations(rows: dict, i: int, parents) -> list:
    """The 24 joints' (3, 3) rotations in the camera's frame at row ``i`` of ``rows`` (poses.npz
    columns: the root's ``Rh`` times the kinematic chain of local rotations)."""
    import cv2
    import numpy as np

    poses = rows["poses"][i].reshape(24, 3).astype(np.float64)
    G = [cv2.Rodrigues(np.asarray(rows["Rh"][i], np.float64))[0] @ cv2.Rodrigues(poses[0])[0]]
    for j in range(1, 24):
        G.append(G[parents[j]] @ cv2.Rodrigues(poses[j])[0])
    return G


def chain_true_in_world(tracked: dict, true: dict, joints) -> dict:
    """``tracked``'s rows (poses.npz columns) with ``joints`` turned to their true orientation in
    the camera's frame and every other joint kept at its tracked orientation there (each local
    rotation re-solved from its parent's): which chain's rotations carry the gap, free of what a
    wrong parent does to a swapped local rotation. Global orientation, shape and position stay
    tracked."""
    import cv2

    from stg_node.body import load_body_model

    parents = load_body_model().parents.tolist()
    chosen = set(joints)
    rows = {k: v.copy() for k, v in tracked.items()}

    for i in range(len(rows["poses"])):
        mine, theirs = joint_world_rotations(tracked, i, parents), joint_world_rotations(true, i, parents)
        target = [theirs[j] if j in chosen else mine[j] for j in range(24)]
        poses = rows["poses"][i].reshape(24, 3)
        for j in range(1, 24):
            poses[j] = cv2.Rodrigues(target[parents[j]].T @ target[j])[0].ravel()
        rows["poses"][i] = poses.reshape(-1)
    return rows


def toward_truth(tracked: dict, true: dict, alpha: float, which: str = "all") -> dict:
    """``tracked``'s rows (poses.npz columns, camera frame) moved a fraction ``alpha`` of the way to
    ``true``'s: every local rotation and the global orientation along the shortest arc, position
    and shape in a straight line (0: as tracked, 1: the truth); ``which="joints"``: the local
    joint rotations alone, ``"body"``: the global orientation, position and shape alone, the rest
    as tracked. How the avatar's score grows as the tracker's error shrinks, whatever the lever."""
    import cv2
    import numpy as np

    rows = {k: v.copy() for k, v in tracked.items()}

    def slerp(a, b):
        Ra, Rb = cv2.Rodrigues(np.asarray(a, np.float64))[0], cv2.Rodrigues(np.asarray(b, np.float64))[0]
        step = cv2.Rodrigues(alpha * cv2.Rodrigues(Ra.T @ Rb)[0])[0]
        return cv2.Rodrigues(Ra @ step)[0].ravel()

    for i in range(len(rows["poses"])):
        mine, theirs = tracked["poses"][i].reshape(24, 3), true["poses"][i].reshape(24, 3)
        if which != "body":
            rows["poses"][i] = np.stack([slerp(mine[j], theirs[j]) for j in range(24)]).reshape(-1)
        if which != "joints":
            rows["Rh"][i] = slerp(tracked["Rh"][i], true["Rh"][i])
    for key in () if which == "joints" else ("Th", "shapes"):
        rows[key] = (1.0 - alpha) * tracked[key] + alpha * true[key]
    return rows


def two_pass_folder(tracked: Path, two_pass: Path) -> Path:
    """``tracked`` (a ``pose_variants`` folder) with its training frames' poses from ``twopass``'s
    average of the forward and backward fits (``two_pass``, run ``twopass`` first); the frames
    after them as tracked. The folder ``twopass`` beside ``tracked``."""

    import numpy as np

    from stg_node.safe_load import load_npz

    if not two_pass.is_file():
        raise FileNotFoundError(f"{two_pass}: run bench_footage.py twopass for this subject first")
    rows = {k: np.asarray(v).copy() for k, v in load_npz(tracked / "poses.npz").items()}
    average = np.asarray(load_npz(two_pass)["average"])
    n = len(average)
    rows["poses"][:n], rows["Rh"][:n], rows["Th"][:n] = average[:, :72], average[:, 72:75], average[:, 75:]
    return write_pose_variant(tracked.parent / "twopass", tracked, rows)


def slid_to_depth(Th, pelvis, depth: float):
    """The translation ``Th`` that moves a body (camera frame) along the ray through its ``pelvis``
    until the pelvis is ``depth`` away: the pelvis's pixel unchanged, its distance changed."""
    import numpy as np

    pelvis = np.asarray(pelvis, np.float64)
    return np.asarray(Th, np.float64) + pelvis * (depth / pelvis[2] - 1.0)


def sources(args) -> dict:
    """Where the tracked-pose gap comes from: the tracked run's own images and masks trained with
    the tracked poses, with the true global orientation, and with the true poses (each with
    today's refinement for tracked poses; the true poses also with the light touch for given
    ones), beside the ground-truth run, all at ``--train-size``."""
    from stg_node.avatar.pose_refine import REFINEMENTS
    from stg_node.avatar.video import prepare_video

    out = args.out
    data = subject(out, f"mixed_{args.size}", num_frames=args.frames, size=args.size)
    video_data = out / "sources" / f"video_data_{args.size}"
    if not (video_data / "poses.npz").is_file():
        prepare_video(data / "Camera_B1", video_data, intrinsics=intrinsics_file(data), progress=False)
    folders = pose_variants(video_data, data, out / "sources" / f"data_{args.size}")
    size = str(args.train_size or args.size)

    def refine(source: str) -> list[str]:
        r = REFINEMENTS[source]
        return ["--set", f"lr_pose={r.lr_pose}", "--set", f"loss.pose_refine={r.pose_refine}",
                "--set", f"loss.pose_smooth={r.pose_smooth}"]  # fmt: skip

    frames = ["--train-frames", f"0:{round(0.8 * args.frames)}", "--size", size]
    runs = {"truth": ("--data", str(data), "--format", "synthetic", "--size", size)}
    for name, source in (("tracked", "tracked"), ("true-orientation", "tracked"), ("true", "tracked"),
                         ("true, light refinement", "given")):  # fmt: skip
        folder = folders[name.split(",")[0]]
        runs[name] = ("--data", str(folder), "--format", "folder", *frames, *refine(source))
    rows = {}
    for name, flags in runs.items():
        slug = name.replace(", ", "_").replace(" ", "_").replace("-", "_")
        run = train(out, f"sources_{slug}_{args.size}_{size}", args, *flags)
        rows[name] = score(run, data, "novel_view")
        if name != "truth":
            rows[name]["similarity"] = score(run, data, "novel_view", align="similarity", parts=False)
    for name in rows:
        rows[name]["below_truth_db"] = rows["truth"]["psnr"] - rows[name]["psnr"]
    return rows


CORRECTED = ["--set", f"lr_exposure={FOOTAGE_RATE}"]  # as --format video trains (for_footage)
EXPOSURE_RUNS = {  # name -> (subject, stg-train settings); --runs picks by the short name
    "steady": ("steady, corrected", "steady", CORRECTED),
    "jitter": ("jitter, corrected", "jitter", CORRECTED),
    "nocorr": ("jitter, not corrected", "jitter", ["--set", "lr_exposure=0"]),
    "steady-nocorr": ("steady, not corrected (the default)", "steady", ["--set", "lr_exposure=0"]),
}


def exposure(args) -> dict:
    out = args.out
    subjects = {
        "steady": subject(out, f"mixed_{args.size}", num_frames=args.frames, size=args.size),
        "jitter": subject(
            out, f"mixed_jitter_{args.size}", num_frames=args.frames, size=args.size, exposure_jitter=0.15
        ),
    }
    common = ["--format", "synthetic", "--size", str(args.size)]
    wanted = wanted_runs(args.runs, EXPOSURE_RUNS, "exposure")
    rows = {}
    for key in wanted:
        name, which, extra = EXPOSURE_RUNS[key]
        folder = f"exp_{key.replace('-', '_')}_{args.size}"
        run = train(out, folder, args, "--data", str(subjects[which]), *common, *extra)
        rows[name] = score(run, subjects[which], "novel_view", parts=False)
        rows[name]["gains"] = learnt_gains(run, subjects[which])
    if "steady" in rows:
        for name in rows:
            rows[name]["below_steady_db"] = rows["steady"]["psnr"] - rows[name]["psnr"]
    return rows


def learnt_gains(run: Path, data: Path) -> dict:
    """How well the run's per-frame gains found the subject's true ones: the RMS error of the log-gains
    (each side's mean removed), beside that of no correction, and the slope of learnt on true."""
    import numpy as np

    from stg_node.avatar import checkpoint
    from stg_node.avatar.exposure import log_gain_error

    meta = json.loads((data / "synth.json").read_text())
    gains = (meta.get("filming") or {}).get("exposure_gains")
    n = int(meta["num_train_frames"])
    truth = {i: np.asarray(gains[i]) if gains else np.ones(3) for i in range(n)}
    state = checkpoint.load(run / "checkpoint.stgsnap").exposure
    learnt = {f: np.ones(3) for f in truth}
    if "frames" in state:
        logs = np.asarray(state["gains"], np.float64).reshape(-1, 3)
        seen = np.asarray(state["steps"]) > 0
        logs = np.where(seen[:, None], logs - logs[seen].mean(axis=0), 0.0) if seen.any() else logs * 0
        learnt.update({int(f): np.exp(logs[i]) for i, f in enumerate(np.asarray(state["frames"]))})
    frames = sorted(truth)
    a = np.log(np.stack([learnt[f] for f in frames]))
    b = np.log(np.stack([truth[f] for f in frames]))
    b_centred = b - b.mean(axis=0)
    slope = float((a - a.mean(axis=0)).ravel() @ b_centred.ravel() / max(float((b_centred**2).sum()), 1e-12))
    return {
        "log_gain_rms": log_gain_error(learnt, truth),
        "log_gain_rms_uncorrected": log_gain_error({f: np.ones(3) for f in frames}, truth),
        "slope_on_truth": slope,
    }


def size(args) -> dict:
    """The same turning subject filmed close and from afar (module docstring)."""
    from stg_node.avatar import preset
    from stg_node.avatar.budget import SCALED, setting_value

    out = args.out
    common = dict(num_frames=args.frames, size=args.size, fov_deg=55.0, motion="turn")
    close = subject(out, f"close_{args.size}_{args.close_m:g}m", camera_distance=args.close_m, **common)
    far = subject(out, f"far_{args.size}_{args.far_m:g}m", camera_distance=args.far_m, **common)
    flags = ["--format", "synthetic", "--size", str(args.size)]
    base = preset(args.preset)

    def kept(keys) -> list[str]:  # --set each of ``keys`` to the preset's own value
        return [item for key in keys for item in ("--set", f"{key}={setting_value(base, key)}")]

    pixel_keys = [key for key in SCALED if key not in SIZE_BUDGET_KEYS]
    plans = {  # --runs name -> (subject, extra flags)
        "far": (far, []),
        "close-fixed": (close, kept(SCALED)),  # the preset's budget
        "close-gs": (close, kept(pixel_keys)),  # the Gaussians and steps scaled, pixel settings held
        "close": (close, []),  # the scaled budget
    }
    wanted = wanted_runs(args.runs, plans, "size")
    far_height = _person_height(far, args.size)
    results = out / "results" / "size_rows"
    results.mkdir(parents=True, exist_ok=True)
    for name in wanted:
        data, extra = plans[name]
        folder = f"size_{name.replace('-', '_')}_{args.size}_{args.close_m:g}m_{args.far_m:g}m"
        run = train(out, folder, args, "--data", str(data), *flags, *extra)
        height = _person_height(data, args.size)
        row = {
            "person_height_px": height,
            "bbox": score(run, data, "novel_view", protocol="bbox", parts=False),
            # the person's box at the far subject's resolution of the person (area-averaged)
            "bbox_at_far_size": score(
                run, data, "novel_view", protocol="bbox", parts=False, resample=min(1.0, far_height / height)
            ),
            "full": score(run, data, "novel_view", parts=False),
        }
        (results / f"{folder}.json").write_text(json.dumps(row, default=float) + "\n")
    rows = {}  # every row scored so far (other processes may have run other --runs)
    finished = {}
    for name in plans:
        folder = f"size_{name.replace('-', '_')}_{args.size}_{args.close_m:g}m_{args.far_m:g}m"
        cached = results / f"{folder}.json"
        if cached.is_file():
            rows[name] = json.loads(cached.read_text())
            finished[name] = (out / "runs" / folder, plans[name][0])
    if args.figure is not None:
        size_figure(finished, args.figure, args.size)
    return rows


def size_figure(runs: dict, path: Path, size: int, view: int | None = None) -> None:
    """One held-out view of every run in ``runs`` (name -> (run folder, subject)), each person's box
    beside the truth, all scaled to the same height (area-averaged down, linear up) and labelled."""
    import cv2
    import numpy as np

    from stg_node.avatar.data_spec import DataSpec
    from stg_node.avatar.loading import corrected, load_run_renderer
    from stg_node.data.metrics.report import mask_bbox

    height = 360
    tiles = {}
    for name, (run, data) in runs.items():
        views = DataSpec(str(data.resolve()), "synthetic", None, None, size).open("novel_view")
        sample = views[view if view is not None else len(views) // 2]
        _, renderer, corrections, _ = load_run_renderer(run)
        smpl = corrected(sample.smpl, corrections.get(sample.index))
        image = renderer.render(sample.camera, smpl, sample.time).image.astype(np.float32) / 255.0  # uint8
        truth = np.where(sample.mask[..., None] > 127, sample.image, 0).astype(np.float32) / 255.0
        x, y, w, h = mask_bbox(sample.mask)
        pad = max(4, h // 20)
        x0, y0 = max(0, x - pad), max(0, y - pad)
        pair = [a[y0 : y + h + pad, x0 : x + w + pad] for a in (truth, image)]
        scale = height / pair[0].shape[0]
        shape = (max(1, round(pair[0].shape[1] * scale)), height)
        how = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
        if "far" not in tiles and name == "far":
            tiles["truth, far"] = cv2.resize(pair[0], shape, interpolation=how)
        elif name != "far" and "truth, close" not in tiles:
            tiles["truth, close"] = cv2.resize(pair[0], shape, interpolation=how)
        tiles[name] = cv2.resize(pair[1], shape, interpolation=how)
    columns = []
    for label, tile in tiles.items():
        tile = np.ascontiguousarray((np.clip(tile, 0, 1) * 255).astype(np.uint8)[..., ::-1])
        cv2.putText(tile, label, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
        columns += [tile, np.full((height, 4, 3), 255, np.uint8)]
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.concatenate(columns[:-1], axis=1))
    log.info("wrote %s", path)


SIZE_BUDGET_KEYS = ("model.num_gaussians", "model.max_gaussians", "densify.flow_max_new", "iterations")


def _person_height(data: Path, size: int) -> float:
    """The median person height (px) in the held-out views of an stg-synth subject."""
    from stg_node.avatar.budget import person_size
    from stg_node.avatar.data_spec import DataSpec

    views = DataSpec(str(data.resolve()), "synthetic", None, None, size).open("novel_view")
    step = max(1, len(views) // 40)
    return person_size(views[i].mask for i in range(0, len(views), step))[1]


def focal(args) -> dict:
    from stg_node.tracking.pipeline import TrackOptions, track_to_file
    from stg_node.tracking.poses_file import read_poses

    out = args.out
    cases = [
        ("approach", fov, {30: 6.0, 45: 4.5, 60: 3.5, 75: 3.0, 90: 2.5}[fov]) for fov in (30, 45, 60, 75, 90)
    ]
    cases += [("still", 45, 4.5), ("still", 75, 3.0)]
    rows = {}
    for motion, fov, distance in cases:
        name = f"{motion}_{fov}"
        filmed = dict(motion=motion, fov_deg=float(fov), camera_distance=distance)
        data = subject(
            out, f"focal_{name}", num_frames=args.focal_frames, size=args.size, num_novel_views=0, **filmed
        )
        poses = out / "focal" / f"{name}.npz"
        t0 = time.perf_counter()
        summary = track_to_file(data / "Camera_B1", poses, TrackOptions(fps=30.0), progress=False)
        camera = json.loads(read_poses(poses).camera)
        rows[name] = {
            "motion": motion,
            "distance_m": distance,
            "true_fov_deg": fov,
            "estimate_fov_deg": camera["fov_deg"],
            "interval_deg": [camera["low_fov_deg"], camera["high_fov_deg"]],
            "error_percent": 100
            * (math.tan(math.radians(fov) / 2) / math.tan(math.radians(camera["fov_deg"]) / 2) - 1),
            "sure": camera["sure"],
            "rise_percent": 100 * camera.get("rise", 0.0),  # the profile's depth (focal.MIN_RISE)
            "reason": camera["reason"],
            "used": camera["used"],
            "seconds": time.perf_counter() - t0,
            "text": summary.camera,
        }
    return rows


def framing(args) -> dict:
    from stg_node.avatar.animation import render_run

    rows = {}
    for views in ("orbit", "follow"):
        target = args.out / "framing" / f"{args.run.name}_{views}.mp4"
        summary = render_run(args.run, target, views=views, show_progress=False)
        rows[views] = summary.framing.as_dict()
    return rows


# refine: the variants of the pose refinement trained on the tracked folder dataset, as --set flags
# on top of today's refinement for tracked poses (pose_refine.REFINEMENTS["tracked"]).
REFINE_VARIANTS = {
    "tracked": (),
    "no refinement": ("lr_pose=0",),
    "warm-up x10": ("pose_warmup_boost=10",),
    "mask x3": ("loss.mask=0.3",),
    "smooth x10": ("loss.pose_smooth=0.01",),
    "non-rigid on": ('nonrigid="on"',),
}


def refine(args) -> dict:
    """The tracked-pose gap and what each pose-refinement variant buys: ``stg-train --format
    video``'s own preparation of the training camera (the ``gap`` experiment's tracked run, tracked
    once) trained as a folder dataset with each variant of ``REFINE_VARIANTS`` (``--runs`` picks),
    beside ``truth``; novel views (training frames, held-out cameras, the refined training poses)
    and novel poses (held-out frames, the tracker's poses as tracked), per body part, and how far
    the refined training poses are from the truth against the tracked ones."""
    from stg_node.avatar.pose_refine import REFINEMENTS
    from stg_node.avatar.video import prepare_video

    out = args.out
    data = subject(out, f"mixed_{args.size}", num_frames=args.frames, size=args.size)
    video_data = out / "refine" / f"video_data_{args.size}"
    if not (video_data / "poses.npz").is_file():
        prepare_video(data / "Camera_B1", video_data, intrinsics=intrinsics_file(data), progress=False)
    r = REFINEMENTS["tracked"]
    tracked = [
        f"lr_pose={r.lr_pose}",
        f"loss.pose_refine={r.pose_refine}",
        f"loss.pose_smooth={r.pose_smooth}",
    ]
    frames = ["--train-frames", f"0:{round(0.8 * args.frames)}", "--size", str(args.size)]
    wanted = wanted_runs(args.runs, ["truth", *REFINE_VARIANTS], "refine")
    rows = {}
    for name in wanted:
        slug = name.replace(" ", "_").replace("-", "_").replace(",", "")
        if name == "truth":
            flags = ("--data", str(data), "--format", "synthetic", "--size", str(args.size))
        else:
            sets = [x for kv in (*tracked, *REFINE_VARIANTS[name]) for x in ("--set", kv)]
            flags = ("--data", str(video_data), "--format", "folder", *frames, *sets)
        run = train(out, f"refine_{slug}_{args.size}_s{args.seed}", args, *flags)
        rows[name] = {split: score(run, data, split) for split in ("novel_view", "novel_pose")}
        if name != "truth":
            rows[name]["poses"] = refined_pose_accuracy(run, video_data, data)
        cached = out / "results" / f"refine_{slug}_{args.size}_s{args.seed}.json"
        cached.parent.mkdir(parents=True, exist_ok=True)
        cached.write_text(json.dumps(rows[name], default=float) + "\n")
    for name in ("truth", *REFINE_VARIANTS):  # rows another process scored
        slug = name.replace(" ", "_").replace("-", "_").replace(",", "")
        cached = out / "results" / f"refine_{slug}_{args.size}_s{args.seed}.json"
        if name not in rows and cached.is_file():
            rows[name] = json.loads(cached.read_text())
    if "truth" in rows:
        for row in rows.values():
            truth = rows["truth"]
            row["gap_db"] = {s: truth[s]["psnr"] - row[s]["psnr"] for s in ("novel_view", "novel_pose")}
    return rows


def refined_pose_accuracy(run: Path, video_data: Path, data: Path) -> dict:
    """The training frames' poses, as tracked and as refined by ``run``, against the truth in the
    training camera's frame: each joint's rotation error (mean, and per group), the global
    orientation's, and the pelvis's distance from the camera (mm, mean absolute, after the
    sequence's one depth ratio that the scoring fixes: :func:`tracked_alignment`'s scale)."""
    import cv2
    import numpy as np

    from stg_node.avatar.loading import corrected, load_run_renderer
    from stg_node.body.motion import load_smpl_params
    from stg_node.safe_load import load_npy, load_npz

    _, _, corrections, _ = load_run_renderer(run)
    frames = np.asarray(load_npz(video_data / "poses.npz")["frames"]).astype(int)
    sequence = load_smpl_params(video_data / "poses.npz")
    R1 = np.asarray(load_npy(data / "annots.npy")["cams"]["R"][0], np.float64)
    from stg_node.avatar.data_spec import DataSpec
    from stg_node.avatar.synth_eval import _joints, tracked_alignment
    from stg_node.body import load_body_model

    body = load_body_model()
    truth_spec = DataSpec(str(data.resolve()), "synthetic", None, None, None).open("train")
    camera = truth_spec.camera(truth_spec.camera_names[0])
    t1 = np.asarray(camera.t, np.float64).reshape(3)
    true_pelvis = _joints(body, [truth_spec.smpl(int(f)) for f in frames])[:, 0] @ R1.T + t1
    tracked_all = _joints(body, [sequence[i] for i in range(len(sequence))])
    gauge = tracked_alignment(
        camera, _joints(body, [truth_spec.smpl(int(f)) for f in frames]), tracked_all
    ).scale
    rows = {"tracked": ([], []), "refined": ([], []), "truth": ([], [])}
    depth = {"tracked": [], "refined": []}
    for i, frame in enumerate(frames):
        if int(frame) not in corrections:
            continue  # a held-out frame
        refined_pelvis = _joints(body, [corrected(sequence[i], corrections[int(frame)])])[0, 0]
        for name, pelvis in (("tracked", tracked_all[i, 0]), ("refined", refined_pelvis)):
            depth[name].append(abs(pelvis[2] / gauge - true_pelvis[i, 2]) * 1000.0)
        true = load_npy(data / "new_params" / f"{int(frame)}.npy")
        true_poses = np.asarray(true["poses"], np.float64).reshape(24, 3)
        rotation = R1 @ cv2.Rodrigues(np.asarray(true["Rh"], np.float64).reshape(3))[0]
        rows["truth"][0].append(true_poses[1:])
        rows["truth"][1].append(cv2.Rodrigues(rotation @ cv2.Rodrigues(true_poses[0])[0])[0].ravel())
        refined = corrected(sequence[i], corrections[int(frame)])
        for name, smpl in (("tracked", sequence[i]), ("refined", refined)):
            poses = np.asarray(smpl.poses, np.float64).reshape(24, 3)
            rh = cv2.Rodrigues(np.asarray(smpl.Rh, np.float64).reshape(3))[0]
            rows[name][0].append(poses[1:])
            rows[name][1].append(cv2.Rodrigues(rh @ cv2.Rodrigues(poses[0])[0])[0].ravel())
    true_joints, true_global = (np.stack(v) for v in rows["truth"])
    result = {"frames": len(true_global)}
    for name in ("tracked", "refined"):
        joints, global_ = (np.stack(v) for v in rows[name])
        err = rotation_angles_deg(joints, true_joints).reshape(len(joints), 23).mean(axis=0)
        result[name] = {
            "joint_rotation_deg": float(err.mean()),
            **{g: float(err[[j - 1 for j in js]].mean()) for g, js in JOINT_GROUPS.items()},
            "global_orientation_deg": float(rotation_angles_deg(global_, true_global).mean()),
            "pelvis_depth_mm": float(np.mean(depth[name])),
        }
    return result


TORSO_JOINTS = (3, 6, 9, 12, 13, 14, 15)  # spine, neck, collars, head (the root is Rh, Th)
LIMB_JOINTS = (1, 2, 4, 5, 7, 8, 10, 11, 16, 17, 18, 19, 20, 21, 22, 23)  # legs, arms, hands, feet
LIMB_ROOTS = {1: 0, 2: 0, 16: 13, 17: 14}  # the first joint of each limb: its parent


def limb_roots_in_world(base: dict, donor: dict):
    """(n, 4, 3) local rotations of the limbs' first joints (hips, shoulders) that give ``base``'s
    torso the world orientation of ``donor``'s limbs: a limb's pose relative to a wrong torso
    says little; its orientation in the camera's frame is what the tracker saw."""
    import cv2
    import numpy as np

    from stg_node.body import load_body_model

    parents = load_body_model().parents.tolist()

    out = []
    for i in range(len(base["poses"])):
        mine, theirs = joint_world_rotations(base, i, parents), joint_world_rotations(donor, i, parents)
        out.append([cv2.Rodrigues(mine[p].T @ theirs[j])[0].ravel() for j, p in LIMB_ROOTS.items()])
    return np.asarray(out)


def chains(args) -> dict:
    """Which body chain the tracked-pose gap sits in: the ``refine`` experiment's tracked folder
    trained with the true torso (global orientation, position, shape, spine, neck, collars,
    head) and the tracked limbs (``true torso``), and with the tracked torso and the true limbs
    (``true limbs``); ``true torso world limbs``: the true torso with the tracked limbs turned to
    keep their orientation in the camera's frame (each in the
    training camera's frame, as ``sources`` builds them), the refinement for tracked poses."""
    import shutil

    import numpy as np

    from stg_node.avatar.pose_refine import REFINEMENTS

    out = args.out
    data = subject(out, f"mixed_{args.size}", num_frames=args.frames, size=args.size)
    video_data = out / "refine" / f"video_data_{args.size}"
    if not (video_data / "poses.npz").is_file():
        raise FileNotFoundError(f"{video_data}: run the refine experiment first (it tracks the video)")
    variants = pose_variants(video_data, data, out / "chains" / f"data_{args.size}")
    tracked = {k: np.asarray(v) for k, v in np.load(variants["tracked"] / "poses.npz").items()}
    true = {k: np.asarray(v) for k, v in np.load(variants["true"] / "poses.npz").items()}
    mixes = {"true torso": (true, tracked, LIMB_JOINTS),
             "true limbs": (tracked, true, LIMB_JOINTS),
             "true torso world limbs": (true, tracked, LIMB_JOINTS)}  # fmt: skip
    r = REFINEMENTS["tracked"]
    settings = (
        f"lr_pose={r.lr_pose}",
        f"loss.pose_refine={r.pose_refine}",
        f"loss.pose_smooth={r.pose_smooth}",
    )
    sets = [x for kv in settings for x in ("--set", kv)]
    frames = ["--train-frames", f"0:{round(0.8 * args.frames)}", "--size", str(args.size), *sets]
    wanted = args.runs.split(",") if args.runs else list(mixes)
    rows = {}
    for name in wanted:
        base, donor, joints = mixes[name]
        rows_ = {k: v.copy() for k, v in base.items()}
        poses = rows_["poses"].reshape(len(rows_["poses"]), 24, 3)
        poses[:, list(joints)] = donor["poses"].reshape(len(poses), 24, 3)[:, list(joints)]
        if name == "true torso world limbs":  # the limbs keep the tracked orientation in the world
            poses[:, list(LIMB_ROOTS)] = limb_roots_in_world(base, donor)
        rows_["poses"] = poses.reshape(len(poses), 72)
        slug = name.replace(" ", "_")
        folder = out / "chains" / f"{slug}_{args.size}"
        folder.mkdir(parents=True, exist_ok=True)
        for sub in ("images", "masks"):
            if not (folder / sub).exists():
                (folder / sub).symlink_to((video_data / sub).resolve())
        shutil.copy(video_data / "cameras.json", folder / "cameras.json")
        np.savez(folder / "poses.npz", **rows_)
        run = train(
            out, f"chains_{slug}_{args.size}", args, "--data", str(folder), "--format", "folder", *frames
        )
        rows[name] = {split: score(run, data, split) for split in ("novel_view", "novel_pose")}
        cached = out / "results" / f"chains_{slug}_{args.size}.json"
        cached.parent.mkdir(parents=True, exist_ok=True)
        cached.write_text(json.dumps(rows[name], default=float) + "\n")
    return rows


BONES = {  # joint -> its child: the bone whose orientation in the camera's frame is compared
    "left upper arm": (16, 18),
    "right upper arm": (17, 19),
    "left forearm": (18, 20),
    "right forearm": (19, 21),
    "left thigh": (1, 4),
    "right thigh": (2, 5),
    "spine (chest)": (9, 12),
    "neck": (12, 15),
    "left hand": (20, 22),
    "right hand": (21, 23),
    "left shin": (4, 7),
    "right shin": (5, 8),
    "left foot": (7, 10),
    "right foot": (8, 11),
}


def camera_frame_rotations(global_aa, local_aa, parents):
    """(n, 24, 3, 3) each joint's rotation in the camera's frame from (n, 3) global and (n, 23, 3)
    local axis-angle rotations."""
    import numpy as np

    from stg_node.data.synth.rotations import axis_angle_to_matrix

    n = len(global_aa)
    L = axis_angle_to_matrix(np.asarray(local_aa, np.float64).reshape(-1, 3)).reshape(n, 23, 3, 3)
    G = [axis_angle_to_matrix(np.asarray(global_aa, np.float64))]
    for j in range(1, 24):
        G.append(G[parents[j]] @ L[:, j - 1])
    return np.stack(G, axis=1)


def bone_errors(G_true, G_tracked, rest_joints) -> dict:
    """Per bone of :data:`BONES`: the mean angle (degrees) between its true and tracked orientation
    in the camera's frame, and the part of it that is a twist about the bone (swing-twist split of
    the error rotation, in the bone's own frame)."""
    import cv2
    import numpy as np

    bones = {}
    for name, (j, child) in BONES.items():
        axis = rest_joints[child] - rest_joints[j]
        axis /= np.linalg.norm(axis)
        D = np.einsum("nba,nbc->nac", G_true[:, j], G_tracked[:, j])  # the error in the bone's frame
        vec = np.stack([cv2.Rodrigues(d)[0].ravel() for d in D])
        angle = np.linalg.norm(vec, axis=1)
        half = np.sin(angle / 2)[:, None] * vec / np.maximum(angle, 1e-12)[:, None]
        twist = np.abs(np.degrees(2 * np.arctan2(half @ axis, np.cos(angle / 2))))
        bones[name] = {"error_deg": float(np.degrees(angle).mean()), "twist_deg": float(twist.mean())}
    return bones


def errors(args) -> dict:
    """What the tracked poses' errors are: each bone's orientation in the camera's frame against
    the truth, split into the twist about the bone and the rest, the global orientation; and the
    per-joint error after a zero-lag Gaussian smoothing of the tracked trajectory in time (sigma
    in frames), which says whether the errors are jitter or slow biases. The ``refine``
    experiment's tracked folder, every tracked frame."""
    import cv2
    import numpy as np
    import torch

    from stg_node.body import load_body_model
    from stg_node.data.synth.rotations import axis_angle_to_matrix
    from stg_node.safe_load import load_npy, load_npz

    out = args.out
    data = subject(out, f"mixed_{args.size}", num_frames=args.frames, size=args.size)
    video_data = out / "refine" / f"video_data_{args.size}"
    if not (video_data / "poses.npz").is_file():
        raise FileNotFoundError(f"{video_data}: run the refine experiment first (it tracks the video)")
    tracked = {k: np.asarray(v) for k, v in load_npz(video_data / "poses.npz").items()}
    frames = tracked["frames"].astype(int)
    R1 = np.asarray(load_npy(data / "annots.npy")["cams"]["R"][0], np.float64)
    true_local, true_global = [], []
    for f in frames:
        true = load_npy(data / "new_params" / f"{int(f)}.npy")
        poses = np.asarray(true["poses"], np.float64).reshape(24, 3)
        rotation = R1 @ cv2.Rodrigues(np.asarray(true["Rh"], np.float64).reshape(3))[0]
        true_local.append(poses[1:])
        true_global.append(cv2.Rodrigues(rotation @ cv2.Rodrigues(poses[0])[0])[0].ravel())
    true_local, true_global = np.stack(true_local), np.stack(true_global)
    poses = tracked["poses"].reshape(-1, 24, 3).astype(np.float64)
    global_ = np.stack(
        [cv2.Rodrigues(cv2.Rodrigues(rh.astype(np.float64))[0] @ cv2.Rodrigues(p0)[0])[0].ravel()
         for rh, p0 in zip(tracked["Rh"], poses[:, 0], strict=True)]
    )  # fmt: skip
    body = load_body_model()
    parents = body.parents.tolist()
    zeros = torch.zeros(1, 3)
    rest = body(betas=torch.zeros(1, 10), poses=torch.zeros(1, 72), Rh=zeros, Th=zeros).joints[0].numpy()

    G_true = camera_frame_rotations(true_global, true_local, parents)
    G_tracked = camera_frame_rotations(global_, poses[:, 1:], parents)
    bones = bone_errors(G_true, G_tracked, rest)

    def smoothed(aa, sigma):
        n, J = aa.shape[:2]
        M = axis_angle_to_matrix(aa.reshape(-1, 3)).reshape(n, J, 3, 3)
        result = np.empty_like(aa)
        for i in range(n):
            gap = frames - frames[i]
            w = np.exp(-0.5 * (gap / sigma) ** 2) * (np.abs(gap) <= 3 * sigma + 0.5)
            S = np.einsum("n,njab->jab", w / w.sum(), M)
            for j in range(J):
                U, _, Vt = np.linalg.svd(S[j])  # the nearest rotation to the weighted mean
                U[:, -1] *= np.sign(np.linalg.det(U @ Vt))
                result[i, j] = cv2.Rodrigues(U @ Vt)[0].ravel()
        return result

    smoothing = {}
    for sigma in (0.0, 1.0, 2.0, 3.0):
        local = smoothed(poses[:, 1:], sigma) if sigma else poses[:, 1:]
        root = smoothed(global_[:, None], sigma)[:, 0] if sigma else global_
        err = rotation_angles_deg(local, true_local).reshape(len(frames), 23)
        smoothing[f"sigma {sigma:g} frames"] = {
            "joint_rotation_deg": float(err.mean()),
            **{g: float(err.mean(axis=0)[[j - 1 for j in js]].mean()) for g, js in JOINT_GROUPS.items()},
            "global_orientation_deg": float(rotation_angles_deg(root, true_global).mean()),
        }
    return {"frames": len(frames), "bones": bones, "smoothing": smoothing}


JOINT_GROUPS = {  # SMPL joint indices
    "shoulders": (16, 17),
    "elbows": (18, 19),
    "hips": (1, 2),
    "knees": (4, 5),
    "spine": (3, 6, 9),
    "neck_head": (12, 15),
}


JOINT_2D_GROUPS = {  # SMPL joints whose image position says where a limb's end is
    "elbows": (18, 19),
    "wrists": (20, 21),
    "knees": (4, 5),
    "ankles": (7, 8),
    "head": (15,),
}


def rotation_angles_deg(a, b):
    """Angle (degrees) of the relative rotation between matching (..., 3) axis-angle vectors."""
    import numpy as np

    from stg_node.data.synth.rotations import axis_angle_to_matrix
    from stg_node.data.synth.split_distances import rotation_angle_deg

    a, b = np.asarray(a, np.float64).reshape(-1, 3), np.asarray(b, np.float64).reshape(-1, 3)
    return rotation_angle_deg(axis_angle_to_matrix(a), axis_angle_to_matrix(b))


def track_accuracy(data: Path, fit_config, poses_out: Path, smoothing: bool = True) -> dict:
    """Track ``data``'s training camera (true intrinsics) with ``fit_config`` (and the tracker's
    One-Euro smoothing unless told); accuracy vs truth."""
    import cv2
    import numpy as np

    from stg_node.body import load_body_model
    from stg_node.data.io import read_mask
    from stg_node.safe_load import load_npy
    from stg_node.tracking.evaluation import joints_from_params, mpjpe, pa_mpjpe
    from stg_node.tracking.pipeline import TrackOptions, build_tracker
    from stg_node.tracking.silhouette import inside_fraction
    from stg_node.tracking.sources import open_source

    metadata = json.loads((data / "synth.json").read_text())
    annots = load_npy(data / "annots.npy")
    K = np.asarray(annots["cams"]["K"][0], np.float64)
    R = np.asarray(annots["cams"]["R"][0], np.float64)
    t = np.asarray(annots["cams"]["T"][0], np.float64).reshape(3) / 1000.0
    options = TrackOptions(
        intrinsics=str(intrinsics_file(data)), fps=float(metadata["fps"]), smoothing=smoothing
    )
    source = open_source(data / "Camera_B1", options.fps)
    tracker, body = build_tracker(options, source.width, source.height, fit=fit_config)
    rows = {k: [] for k in ("poses", "Rh", "Th", "betas", "mask", "confidence")}
    started = time.perf_counter()
    for frame in source:
        estimate = tracker.estimate(frame.image, frame.timestamp)
        rows["poses"].append(np.asarray(estimate.smpl.poses, np.float64).reshape(24, 3))
        rows["Rh"].append(np.asarray(estimate.smpl.Rh, np.float64))
        rows["Th"].append(np.asarray(estimate.smpl.Th, np.float64))
        rows["betas"].append(np.asarray(estimate.smpl.betas, np.float64))
        rows["mask"].append(estimate.mask)
        rows["confidence"].append(estimate.confidence)
    seconds = time.perf_counter() - started
    n = len(rows["poses"])
    betas = np.tile(np.asarray(tracker.fitter.betas, np.float64), (n, 1))
    poses_out.parent.mkdir(parents=True, exist_ok=True)
    np.savez(poses_out, poses=np.stack(rows["poses"]), Rh=np.stack(rows["Rh"]), Th=np.stack(rows["Th"]),
             betas=betas)  # fmt: skip
    names = sorted((data / "Camera_B1").glob("*.png"))[:n]
    params = [load_npy(data / "new_params" / f"{int(p.stem)}.npy") for p in names]
    true_poses = np.concatenate([p["poses"] for p in params]).reshape(n, 24, 3).astype(np.float64)
    true_Rh = np.concatenate([p["Rh"] for p in params]).astype(np.float64)
    true_Th = np.concatenate([p["Th"] for p in params]).astype(np.float64)
    true_betas = np.concatenate([p["shapes"] for p in params]).astype(np.float64)
    truth_body = load_body_model()
    gt = joints_from_params(truth_body, true_poses, true_Rh, true_Th, true_betas) @ R.T + t
    pred = joints_from_params(
        body, np.stack(rows["poses"]), np.stack(rows["Rh"]), np.stack(rows["Th"]), betas
    )
    joint_err = rotation_angles_deg(np.stack(rows["poses"])[:, 1:], true_poses[:, 1:]).reshape(n, 23)
    true_global = [cv2.Rodrigues(R @ cv2.Rodrigues(rh)[0] @ cv2.Rodrigues(p0)[0])[0].ravel()
                   for rh, p0 in zip(true_Rh, true_poses[:, 0], strict=True)]  # fmt: skip
    global_err = rotation_angles_deg(np.stack(rows["Rh"]), np.stack(true_global))

    def in_mask(b, poses, Rh, Th, betas_, masks) -> np.ndarray:
        import torch

        out = []
        with torch.no_grad():
            for i in range(n):
                posed = b(
                    betas=torch.as_tensor(betas_[i : i + 1], dtype=torch.float32),
                    poses=torch.as_tensor(poses[i].reshape(1, 72), dtype=torch.float32),
                    Rh=torch.as_tensor(Rh[i : i + 1], dtype=torch.float32),
                    Th=torch.as_tensor(Th[i : i + 1], dtype=torch.float32),
                )
                verts = posed.vertices[0].double().numpy()
                if b is truth_body:
                    verts = verts @ R.T + t
                uv = verts @ K.T
                out.append(inside_fraction(uv[:, :2] / uv[:, 2:], masks[i]))
        return np.asarray(out)

    true_masks = [read_mask(data / "mask" / "Camera_B1" / p.name) for p in names]
    tracked_args = (body, np.stack(rows["poses"]), np.stack(rows["Rh"]), np.stack(rows["Th"]), betas)
    own = in_mask(*tracked_args, rows["mask"])
    on_truth = in_mask(*tracked_args, true_masks)
    per_joint = joint_err.mean(axis=0)
    uv_pred, uv_gt = pred @ K.T, gt @ K.T  # the camera's own picture: what a same-camera score sees
    joint_px = np.linalg.norm(uv_pred[..., :2] / uv_pred[..., 2:] - uv_gt[..., :2] / uv_gt[..., 2:], axis=-1)
    return {
        "frames": n,
        "joint_2d_px": {
            "mean": float(joint_px.mean()),
            **{g: float(joint_px[:, list(js)].mean()) for g, js in JOINT_2D_GROUPS.items()},
        },
        "seconds_per_frame": seconds / n,
        "mpjpe_mm": float(mpjpe(pred, gt).mean() * 1000),
        "pa_mpjpe_mm": float(pa_mpjpe(pred, gt).mean() * 1000),
        "joint_rotation_deg": {
            "mean": float(joint_err.mean()),
            "median": float(np.median(joint_err)),
            **{g: float(per_joint[[j - 1 for j in js]].mean()) for g, js in JOINT_GROUPS.items()},
        },  # fmt: skip
        "global_orientation_deg": {
            "mean": float(global_err.mean()),
            "median": float(np.median(global_err)),
            "max": float(global_err.max()),
        },  # fmt: skip
        "mesh_in_own_mask": {"mean": float(own.mean()), "min": float(own.min())},
        "mesh_in_true_mask": {"mean": float(on_truth.mean()), "min": float(on_truth.min())},
        "true_mesh_in_own_mask": float(
            in_mask(truth_body, true_poses, true_Rh, true_Th, true_betas, rows["mask"]).mean()
        ),
        "mean_confidence": float(np.mean(rows["confidence"])),
    }


def fit(args) -> dict:
    """Tracking accuracy with the fit's silhouette term off and on (interleaved per --repeats)."""
    import dataclasses

    from stg_node.tracking.fitting import FitConfig

    data = subject(args.out, f"mixed_{args.size}", num_frames=args.frames, size=args.size)
    off = dataclasses.replace(FitConfig(), silhouette_weight=0.0)
    variants = {
        "keypoints only": (off, True),
        "silhouette": (FitConfig(), True),
        "keypoints only, unsmoothed": (off, False),
        "silhouette, unsmoothed": (FitConfig(), False),
    }
    wanted = args.runs.split(",") if args.runs else ["accuracy"]
    rows = {}
    for name, (config, smoothing) in variants.items():
        if "accuracy" not in wanted:
            break
        slug = name.replace(", ", "_").replace(" ", "_")
        rows[name] = track_accuracy(
            data, config, args.out / "fit" / f"{slug}_{args.size}" / "poses.npz", smoothing
        )
        log.info("%s: %s", name, json.dumps(rows[name]))
    trained = [w for w in wanted if w in ("truth", "silhouette", "keypoints", "unsmoothed")]
    if trained:
        rows["training"] = fit_training(args, data, trained)
    return rows


def fit_training(args, data: Path, wanted: list[str]) -> dict:
    """Novel views of runs trained on the tracker's folder dataset (stg-train --format video's own
    preparation: the default fit, silhouette on) and on the same folder with the poses of the
    ``accuracy`` pass's keypoint-only fit (``keypoints``) and unsmoothed silhouette fit
    (``unsmoothed``), same frames, beside ``--format synthetic``."""
    import shutil

    import numpy as np

    from stg_node.avatar.video import prepare_video
    from stg_node.safe_load import load_npz

    out = args.out
    video_data = out / "fit" / f"video_data_{args.size}"
    if not (video_data / "poses.npz").is_file():
        prepare_video(data / "Camera_B1", video_data, intrinsics=intrinsics_file(data), progress=False)
    swapped = {}
    for name, accuracy_pass in (("keypoints", "keypoints_only"), ("unsmoothed", "silhouette_unsmoothed")):
        folder = swapped[name] = out / "fit" / f"{name}_data_{args.size}"
        if (folder / "poses.npz").is_file():
            continue
        plain = np.load(out / "fit" / f"{accuracy_pass}_{args.size}" / "poses.npz")
        rows = {k: np.asarray(v).copy() for k, v in load_npz(video_data / "poses.npz").items()}
        index = rows["frames"].astype(int)
        rows["poses"] = plain["poses"][index].reshape(len(index), -1).astype(rows["poses"].dtype)
        rows["Rh"], rows["Th"] = plain["Rh"][index].astype(np.float32), plain["Th"][index].astype(np.float32)
        rows["shapes"][:] = plain["betas"][0, : rows["shapes"].shape[1]]
        folder.mkdir(parents=True, exist_ok=True)
        for sub in ("images", "masks"):
            if not (folder / sub).exists():
                (folder / sub).symlink_to((video_data / sub).resolve())
        shutil.copy(video_data / "cameras.json", folder / "cameras.json")
        np.savez(folder / "poses.npz", **rows)
    frames = ["--train-frames", f"0:{round(0.8 * args.frames)}", "--size", str(args.size)]
    runs = {
        "truth": ("--data", str(data), "--format", "synthetic", "--size", str(args.size)),
        "silhouette": ("--data", str(video_data), "--format", "folder", *frames),
        "keypoints": ("--data", str(swapped["keypoints"]), "--format", "folder", *frames),
        "unsmoothed": ("--data", str(swapped["unsmoothed"]), "--format", "folder", *frames),
    }
    result = {}
    for name in runs:
        run = out / "runs" / f"fit_{name}_{args.size}"
        if name in wanted:
            train(out, run.name, args, *runs[name])
        if (run / "summary.json").is_file() and json.loads((run / "summary.json").read_text()).get(
            "finished"
        ):
            result[name] = score(run, data, "novel_view")
    for name in result:
        if "truth" in result:
            result[name]["below_truth_db"] = result["truth"]["psnr"] - result[name]["psnr"]
    return result


CLOSEUP_RUNS = ("truth", "tracked", "true-poses")


def closeup_subject(args) -> Path:
    """A dancer (fast, large arm and leg swings, twisting) in the striped shirt, filling the frame
    (``--closeup-m`` from a 55 degree camera), facing the camera within a 90 degree window: the
    shape of a martial-arts clip. Frames after the generator's training range are new poses."""
    return subject(
        args.out,
        f"closeup_{args.size}_{args.frames}_{args.closeup_m:g}m",
        motion="dance",
        num_frames=args.frames,
        size=args.size,
        camera_distance=args.closeup_m,
        fov_deg=55.0,
        train_yaw_deg=90.0,
    )


def closeup(args) -> dict:
    """Held-out frames of the training camera (module docstring): ``truth`` (``--format
    synthetic``), ``tracked`` (``--format video``: the tracker's poses and masks, its poses for the
    held-out frames as tracked) and ``true-poses`` (the tracked run's own images, masks and camera
    with the true parameters for every frame: what the pipeline costs without pose errors)."""
    from stg_node.avatar.video import prepare_video

    out = args.out
    data = closeup_subject(args)
    tag = f"{args.size}_{args.frames}_{args.closeup_m:g}m_s{args.seed}"
    n_train = round(0.8 * args.frames)
    frames = ["--train-frames", f"0:{n_train}", "--size", str(args.size)]
    video = camera_video_args(data)
    wanted = wanted_runs(args.runs, CLOSEUP_RUNS, "closeup")
    rows = {}
    for name in wanted:
        if name == "truth":
            flags = ("--data", str(data), "--format", "synthetic", "--size", str(args.size))
        elif name == "tracked":
            flags = (*video, *frames)
        else:  # the true parameters in the tracker's world, trained as the tracked run trains
            video_data = out / "closeup" / f"video_data_{args.size}_{args.frames}_{args.closeup_m:g}m"
            if not (video_data / "poses.npz").is_file():
                prepare_video(
                    data / "Camera_B1", video_data, intrinsics=intrinsics_file(data), progress=False
                )
            folder = pose_variants(video_data, data, out / "closeup" / f"data_{tag}")["true"]
            flags = ("--data", str(folder), "--format", "folder", *frames, *as_video_trains())
        run = train(out, f"closeup_{name.replace('-', '_')}_{tag}", args, *flags)
        rows[name] = closeup_scores(run, data)
        cached = out / "results" / f"closeup_{name}_{tag}.json"
        cached.parent.mkdir(parents=True, exist_ok=True)
        cached.write_text(json.dumps(rows[name], default=float) + "\n")
    for name in CLOSEUP_RUNS:  # rows another process scored
        cached = out / "results" / f"closeup_{name}_{tag}.json"
        if name not in rows and cached.is_file():
            rows[name] = json.loads(cached.read_text())
    if "truth" in rows:
        for row in rows.values():
            row["gap_db"] = gap_by_part(rows["truth"], row)
    return rows


def as_video_trains() -> list[str]:
    """The ``--set`` flags that make a folder dataset train as ``--format video`` trains (the
    refinement for tracked poses, the per-frame colour correction)."""
    from stg_node.avatar.pose_refine import REFINEMENTS

    r = REFINEMENTS["tracked"]
    sets = [f"lr_pose={r.lr_pose}", f"loss.pose_refine={r.pose_refine}", f"loss.pose_smooth={r.pose_smooth}",
            f"lr_exposure={FOOTAGE_RATE}"]  # fmt: skip
    return [x for kv in sets for x in ("--set", kv)]


def closeup_scores(run: Path, data: Path) -> dict:
    """A run on the closeup subject: held-out frames of the training camera (the tracker's poses
    for a tracked run) and novel views, per body part."""
    return {
        "held_out_same_camera": score(run, data, "novel_pose", same_camera=True),
        "novel_view": score(run, data, "novel_view"),
    }


def gap_by_part(truth: dict, row: dict) -> dict:
    """Truth's PSNR minus ``row``'s, overall and per body part, for each split both scored."""
    result = {}
    for split in truth:
        if split not in row or not isinstance(truth[split], dict) or "psnr" not in truth[split]:
            continue
        mine, theirs = row[split], truth[split]
        result[split] = {
            "psnr": theirs["psnr"] - mine["psnr"],
            "lpips": mine["lpips"] - theirs["lpips"],
            "parts": {
                part: theirs["parts_psnr"][part] - mine["parts_psnr"][part]
                for part in theirs.get("parts_psnr", {})
                if part in mine.get("parts_psnr", {})
            },
        }
    return result


#: decompose's steps: each row renders the tracked run's avatar with more of the truth put in.
DECOMPOSE_STEPS = {
    "score": {},
    "similarity": {"align": "similarity"},
    "true-root": {"root": "true"},
    "true-root-orientation": {"root": "true", "swap": "orientation"},
    "true-root-pose": {"root": "true", "swap": "pose"},
}


def decompose(args) -> dict:
    """Where the tracked run's gap goes, without training anything new: the ``gap`` subject's
    tracked and truth runs (trained if missing) and, with ``--runs closeup``, the closeup
    subject's. The tracked avatar is rendered with, in turn, the one similarity for the sequence
    in place of the camera's extrinsics (the world's gauge), each frame's pelvis at the true one
    (the single camera's depth), the true global orientation as well, and the true joint rotations
    as well (the tracked shape kept). What the last row still lacks from the truth run is the
    avatar itself: what it learnt from the tracked training poses."""
    which = wanted_runs(args.runs or "gap", ("gap", "closeup", "gap-trained", "closeup-trained"), "decompose")
    rows = {}
    for subject_name in which:
        if subject_name.endswith("-trained"):
            rows[subject_name] = decompose_trained(args, subject_name.removesuffix("-trained"))
            continue
        if subject_name == "gap":
            data = subject(args.out, f"mixed_{args.size}", num_frames=args.frames, size=args.size)
            video = [*camera_video_args(data), "--train-frames", f"0:{round(0.8 * args.frames)}",
                     "--size", str(args.size)]  # fmt: skip
            truth = train(args.out, f"gap_truth_{args.size}", args, "--data", str(data), "--format",
                          "synthetic", "--size", str(args.size))  # fmt: skip
            tracked = train(args.out, f"gap_tracked_{args.size}", args, *video)
            splits = {"novel_view": {}, "novel_pose": {}}
        else:
            data = closeup_subject(args)
            tag = f"{args.size}_{args.frames}_{args.closeup_m:g}m_s{args.seed}"
            truth = train(args.out, f"closeup_truth_{tag}", args, "--data", str(data), "--format",
                          "synthetic", "--size", str(args.size))  # fmt: skip
            frames = ["--train-frames", f"0:{round(0.8 * args.frames)}", "--size", str(args.size)]
            tracked = train(args.out, f"closeup_tracked_{tag}", args, *camera_video_args(data), *frames)
            splits = {"novel_view": {}, "held_out_same_camera": {"same_camera": True}}
        result = {}
        for split, kw in splits.items():
            name = "novel_pose" if split == "held_out_same_camera" else split
            baseline = score(truth, data, name, **kw)
            steps = {step: score(tracked, data, name, **kw, **more) for step, more in DECOMPOSE_STEPS.items()}
            result[split] = decomposition(baseline, steps)
        rows[subject_name] = result
    return rows


TOWARD_TRUTH_PERCENT = (50, 75, 90)  # pose_variants' toward-N: the tracked poses N % of the way to the truth

TRAINED_STEPS = (
    "tracked", "true-depth", "true-orientation", "true", "true-arms", "true-legs", "true-torso", "twopass",
    "order-oracle", "order-voted", "order-test", "retracked", "rig",
    *(f"toward-{w}{p}" for w in ("", "joints-", "body-") for p in TOWARD_TRUTH_PERCENT),
)  # fmt: skip


def decompose_tag(args, subject_name: str) -> str:
    """The suffix naming one subject's ``decompose`` runs and folders (``data_{subject}_{tag}``)."""
    if subject_name == "gap":
        return f"{args.size}_s{args.seed}"
    return f"{args.size}_{args.frames}_{args.closeup_m:g}m_s{args.seed}"


def trained_folders(args) -> tuple[str, Path]:
    """(subject, folder) of the training folders ``decompose --runs SUBJECT-trained`` wrote, which the
    later experiments (cues, order, ordertest) read; a clear error if that has not run."""
    name = args.runs or "gap"
    folder = args.out / "decompose" / f"data_{name}_{decompose_tag(args, name)}"
    if not (folder / "true" / "poses.npz").is_file():
        raise FileNotFoundError(f"{folder}: run decompose --runs {name}-trained first")
    return name, folder


def decompose_trained(args, subject_name: str = "gap") -> dict:
    """``decompose --runs gap-trained`` (or ``closeup-trained``): the same question answered by
    training, free of what an avatar learnt on the tracked poses does when rendered with others.
    The tracked run's own folder (its images, masks, camera) trained as ``--format video`` trains,
    with the tracked poses, with each frame's depth made true (``pose_variants``' ``true-depth``),
    with the true global orientation, and with the true parameters; and, to split the joint
    rotations' share by chain, with one chain (:data:`CHAINS`: ``true-arms``, ``true-legs``,
    ``true-torso``) at its true orientation in the camera's frame, the rest as tracked
    (:func:`chain_true_in_world`); scored as the subject's
    experiment scores (gap: novel views and novel poses; closeup: the held-out frames of the
    training camera and novel views)."""
    out = args.out
    frames = ["--train-frames", f"0:{round(0.8 * args.frames)}", "--size", str(args.size)]
    if subject_name == "gap":
        data = subject(out, f"mixed_{args.size}", num_frames=args.frames, size=args.size)
        tracked_run = train(out, f"gap_tracked_{args.size}", args, *camera_video_args(data), *frames)
        truth = train(out, f"gap_truth_{args.size}", args, "--data", str(data), "--format", "synthetic",
                      "--size", str(args.size))  # fmt: skip
        tag = decompose_tag(args, subject_name)

        def scores(run: Path) -> dict:
            return {split: score(run, data, split) for split in ("novel_view", "novel_pose")}
    else:
        data = closeup_subject(args)
        tag = decompose_tag(args, subject_name)
        tracked_run = train(out, f"closeup_tracked_{tag}", args, *camera_video_args(data), *frames)
        truth = train(out, f"closeup_truth_{tag}", args, "--data", str(data), "--format", "synthetic",
                      "--size", str(args.size))  # fmt: skip

        def scores(run: Path) -> dict:
            return closeup_scores(run, data)

    if args.train_set and not args.variant:
        raise ValueError("decompose --set needs --variant NAME (the runs are named after it)")
    settings = [x for kv in args.train_set for x in ("--set", kv)]
    suffix = f"_{args.variant}" if args.variant else ""
    where = out / "decompose" / f"data_{subject_name}_{tag}"
    folders = pose_variants(tracked_run / "video_data", data, where)
    if "twopass" in (args.steps or ""):
        folders["twopass"] = two_pass_folder(
            folders["tracked"], out / "twopass" / f"{subject_name}_{args.size}_s0.npz"
        )
    if "rig" in (args.steps or "").split(","):
        folders["rig"] = rig_folder(args, data, folders["tracked"])
    for name in ("order-oracle", "order-voted", "order-test", "retracked"):
        if name in (args.steps or "").split(","):
            if not (where / name / "poses.npz").is_file():
                raise FileNotFoundError(f"{where / name}: run bench_footage.py order for this subject first")
            folders[name] = where / name
    rows = {"truth": scores(truth)}
    for name in wanted_runs(args.steps, TRAINED_STEPS, "decompose --steps"):
        slug = name.replace("-", "_")
        run = train(out, f"decompose_{subject_name}_{slug}_{tag}{suffix}", args, "--data", str(folders[name]),
                    "--format", "folder", *frames, *as_video_trains(), *settings)  # fmt: skip
        rows[name] = scores(run)
        rows[name]["gap_db"] = gap_by_part(rows["truth"], rows[name])
    return rows


def decomposition(truth: dict, steps: dict) -> dict:
    """The truth run's score, each step's, and what each step gains over the one before (PSNR and
    per part); ``avatar``: what the truth run still scores above the last step."""
    names = list(steps)
    gains = {}
    for before, after in zip(names, names[1:], strict=False):
        mine, theirs = steps[after], steps[before]
        gains[after] = {
            "psnr": mine["psnr"] - theirs["psnr"],
            "parts": {p: mine["parts_psnr"][p] - theirs["parts_psnr"][p] for p in mine["parts_psnr"]},
        }
    last = steps[names[-1]]
    gains["avatar"] = {
        "psnr": truth["psnr"] - last["psnr"],
        "parts": {p: truth["parts_psnr"][p] - last["parts_psnr"][p] for p in truth["parts_psnr"]},
    }
    return {"truth": truth, "steps": steps, "gains": gains, "gap_db": truth["psnr"] - steps[names[0]]["psnr"]}


CUE_BONES = {  # bone -> (SMPL joint, child), (BlazePose point, child)
    "left upper arm": ((16, 18), ("left_shoulder", "left_elbow")),
    "right upper arm": ((17, 19), ("right_shoulder", "right_elbow")),
    "left forearm": ((18, 20), ("left_elbow", "left_wrist")),
    "right forearm": ((19, 21), ("right_elbow", "right_wrist")),
    "left thigh": ((1, 4), ("left_hip", "left_knee")),
    "right thigh": ((2, 5), ("right_hip", "right_knee")),
    "left shin": ((4, 7), ("left_knee", "left_ankle")),
    "right shin": ((5, 8), ("right_knee", "right_ankle")),
}
LENGTH_BONES = {"upper arm": (16, 18), "forearm": (18, 20), "thigh": (1, 4), "shin": (4, 7), "neck": (12, 15)}


def cues(args) -> dict:
    """What evidence for the limbs' depth the tracker has beside its fit, on ``decompose``'s tracked
    folder (``--runs gap`` or ``closeup``; run ``decompose --runs gap-trained`` / ``closeup-trained``
    first): per limb bone, the fit's and BlazePose's metric 3D points' direction in the camera's
    frame against the truth (the angle, its elevation towards the camera, and how often the
    bone's depth order, which end is nearer, is wrong where the true bone leans more than 15
    degrees), the fitted shape's bone lengths against the true ones, and each joint's local
    rotation error with its twist about the bone. A depth-order or direction term from the
    detector's 3D points can only help where they beat the fit."""
    import cv2
    import numpy as np
    import torch

    from stg_node.body import load_body_model
    from stg_node.safe_load import load_npz
    from stg_node.tracking.detectors import make_detector
    from stg_node.tracking.layouts import get_layout

    name, folder = trained_folders(args)
    body = load_body_model()
    parents = body.parents.tolist()
    layout = get_layout("blazepose33")
    rows = {
        k: {c: np.asarray(v) for c, v in load_npz(folder / k / "poses.npz").items()}
        for k in ("tracked", "true")
    }

    def forward(r, poses=None):
        def tensor(x):
            return torch.as_tensor(np.asarray(x), dtype=torch.float32)

        poses = r["poses"] if poses is None else poses
        return body(betas=tensor(r["shapes"][:, :10]), poses=tensor(poses).reshape(len(poses), 72),
                    Rh=tensor(r["Rh"]), Th=tensor(r["Th"]))  # fmt: skip

    fit, true = forward(rows["tracked"]).joints.numpy(), forward(rows["true"]).joints.numpy()
    detector = make_detector("blazepose", threads=1)
    world = []
    for frame in rows["tracked"]["frames"].astype(int):
        image = cv2.imread(str(folder / "tracked" / "images" / "camera" / f"{frame:06d}.jpg"))
        if image is None:
            raise FileNotFoundError(f"{folder}/tracked/images/camera/{frame:06d}.jpg")
        points = detector(cv2.cvtColor(image, cv2.COLOR_BGR2RGB))
        world.append(np.full((33, 3), np.nan) if points is None or points.world is None else points.world)
    world = np.asarray(world, np.float64)

    def unit(v):
        return v / np.linalg.norm(v, axis=-1, keepdims=True)

    def elevation(d):
        return np.degrees(np.arcsin(np.clip(d[:, 2], -1, 1)))

    bones = {}
    for bone, ((j, c), (a, b)) in CUE_BONES.items():
        t = unit(true[:, c] - true[:, j])
        leaning = np.abs(t[:, 2]) > np.sin(np.radians(15))
        row = {}
        for source, d in (("fit", unit(fit[:, c] - fit[:, j])),
                          ("blazepose", unit(world[:, layout.index(b)] - world[:, layout.index(a)])),
                          ):  # fmt: skip
            wrong = np.sign(d[leaning, 2]) != np.sign(t[leaning, 2])
            row[source] = {
                "direction_deg": float(np.nanmean(np.degrees(np.arccos(np.clip((d * t).sum(1), -1, 1))))),
                "elevation_deg": float(np.nanmean(np.abs(elevation(d) - elevation(t)))),
                "depth_order_wrong_pct": float(100 * wrong.mean()) if leaning.any() else float("nan"),
            }
        bones[bone] = row
    rest = {k: forward(r, np.zeros_like(r["poses"])).joints.numpy()[0] for k, r in rows.items()}
    lengths = {bone: float(np.linalg.norm(rest["tracked"][c] - rest["tracked"][j])
                           / np.linalg.norm(rest["true"][c] - rest["true"][j]))
               for bone, (j, c) in LENGTH_BONES.items()}  # fmt: skip
    joints = {}
    child = {}
    for j in range(1, 24):
        child.setdefault(parents[j], j)
    for j in range(1, 24):
        axis = (
            unit(rest["true"][child[j]] - rest["true"][j])
            if j in child
            else unit(rest["true"][j] - rest["true"][parents[j]])
        )
        err, twist = [], []
        for i in range(len(fit)):
            mine = cv2.Rodrigues(rows["tracked"]["poses"][i].reshape(24, 3)[j].astype(np.float64))[0]
            theirs = cv2.Rodrigues(rows["true"]["poses"][i].reshape(24, 3)[j].astype(np.float64))[0]
            vec = cv2.Rodrigues(theirs.T @ mine)[0].ravel()
            angle = np.linalg.norm(vec)
            half = np.sin(angle / 2) * vec / max(angle, 1e-12)
            err.append(np.degrees(angle))
            twist.append(abs(np.degrees(2 * np.arctan2(half @ axis, np.cos(angle / 2)))))
        joints[JOINT_NAMES[j]] = {"error_deg": float(np.mean(err)), "twist_deg": float(np.mean(twist))}
    return {"frames": len(fit), "bones": bones, "bone_length_ratio": lengths, "joints": joints}


def blazepose_world_points(folder: Path, frames):
    """BlazePose's metric 3D points (F, 33, 3; NaN where it found nobody) for ``frames`` of a
    ``pose_variants`` folder's images, detected afresh (the tracker keeps only its fit)."""
    import cv2
    import numpy as np

    from stg_node.tracking.detectors import make_detector

    detector = make_detector("blazepose", threads=1)
    world = []
    for frame in np.asarray(frames).astype(int):
        image = cv2.imread(str(folder / "images" / "camera" / f"{frame:06d}.jpg"))
        if image is None:
            raise FileNotFoundError(f"{folder}/images/camera/{frame:06d}.jpg")
        points = detector(cv2.cvtColor(image, cv2.COLOR_BGR2RGB))
        world.append(np.full((33, 3), np.nan) if points is None or points.world is None else points.world)
    return np.asarray(world, np.float64)


def flipped_direction(p, q):
    """The other direction of the bone from ``p`` to ``q`` (camera frame, metres) that keeps ``q``'s
    pixel and the bone's length: ``q`` slid along its ray to the second root of ``|s u - p| = L``
    (its depth order the other way round). Unit vector."""
    import numpy as np

    u = q / np.linalg.norm(q)
    s2 = 2.0 * float(u @ p) - float(np.linalg.norm(q))
    d = s2 * u - p
    return d / np.linalg.norm(d)


def with_bones_flipped(rows: dict, flips: dict) -> dict:
    """``rows`` (poses.npz columns, camera frame) with each bone ``(j, c)`` of ``flips`` (a boolean
    per row) turned, where set, to :func:`flipped_direction`: ``j``'s rotation in the camera's
    frame pre-multiplied by the smallest rotation between the two directions, every other joint's
    rotation in the camera's frame kept (each local rotation re-solved from its parent's), so only
    that bone's depth order changes."""
    import cv2
    import numpy as np
    import torch

    from stg_node.body import load_body_model

    body = load_body_model()
    parents = body.parents.tolist()

    def tensor(x):
        return torch.as_tensor(np.asarray(x), dtype=torch.float32)

    joints = body(betas=tensor(rows["shapes"][:, :10]), poses=tensor(rows["poses"]).reshape(-1, 72),
                  Rh=tensor(rows["Rh"]), Th=tensor(rows["Th"])).joints.numpy().astype(np.float64)  # fmt: skip
    out = {k: v.copy() for k, v in rows.items()}
    for i in range(len(rows["poses"])):
        G = joint_world_rotations(rows, i, parents)
        changed = False
        for (j, c), mask in flips.items():
            if not mask[i]:
                continue
            p, q = joints[i, j], joints[i, c]
            d = (q - p) / np.linalg.norm(q - p)
            axis = np.cross(d, flipped_direction(p, q))
            angle = math.atan2(np.linalg.norm(axis), float(d @ flipped_direction(p, q)))
            if np.linalg.norm(axis) < 1e-9:
                continue
            G[j] = cv2.Rodrigues(axis / np.linalg.norm(axis) * angle)[0] @ G[j]
            changed = True
        if changed:
            poses = out["poses"][i].reshape(24, 3)
            for j in range(1, 24):
                poses[j] = cv2.Rodrigues(G[parents[j]].T @ G[j])[0].ravel()
            out["poses"][i] = poses.reshape(-1)
    return out


ORDER_MIN_LEAN_DEG = 10.0  # a bone nearer the image plane than this: its depth order is left alone


def voted_flips(fit_joints, world, layout, min_lean_deg: float = ORDER_MIN_LEAN_DEG) -> dict:
    """Per limb bone, the frames whose depth order the detector's 3D points outvote, decided over
    the sequence: the frames where the fitted bone leans towards or away from the camera by more
    than ``min_lean_deg`` form runs of one depth order (a limb changes order only by passing the
    image plane); in each run BlazePose's metric 3D points vote, each frame weighted by how far its
    bone leans (a bone it sees side-on says little), and the run is flipped where the weighted
    vote goes against the fit."""
    import numpy as np

    lean_min = math.sin(math.radians(min_lean_deg))
    flips = {}
    for (j, c), (a, b) in CUE_BONES.values():
        d = fit_joints[:, c] - fit_joints[:, j]
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        ray = fit_joints[:, j] / np.linalg.norm(fit_joints[:, j], axis=-1, keepdims=True)
        towards = -(d * ray).sum(-1)  # > 0: the child end nearer the camera
        w = world[:, layout.index(b)] - world[:, layout.index(a)]
        w_towards = -w[:, 2] / np.linalg.norm(w, axis=-1)  # BlazePose's z points away from the camera
        w_towards = np.nan_to_num(w_towards)
        mask = np.zeros(len(d), bool)
        i = 0
        while i < len(d):
            if abs(towards[i]) < lean_min:
                i += 1
                continue
            k = i
            while (
                k + 1 < len(d)
                and abs(towards[k + 1]) >= lean_min
                and np.sign(towards[k + 1]) == np.sign(towards[i])
            ):
                k += 1
            vote = float(w_towards[i : k + 1].sum())  # signed, weighted by each frame's lean
            if vote * np.sign(towards[i]) < 0:
                mask[i : k + 1] = True
            i = k + 1
        flips[(j, c)] = mask
    return flips


def order(args) -> dict:
    """Each limb bone's depth order (which end is nearer the camera), on ``decompose``'s tracked
    folder (``--runs gap`` or ``closeup``; run ``decompose --runs gap-trained`` / ``closeup-trained``
    first): the tracked poses, the same with every bone's order set by the truth where the other
    order is closer to it (``order-oracle``: what an order decider could be worth at most; a
    diagnostic), and with the order decided over the sequence by the detector's 3D points
    (``order-voted``, :func:`voted_flips`). Each bone's direction in the camera's frame and the
    joints' local rotations against the truth, over the training frames; the two folders are
    written beside ``tracked`` for ``decompose --steps order-oracle,order-voted``."""
    import numpy as np
    import torch

    from stg_node.body import load_body_model
    from stg_node.safe_load import load_npz
    from stg_node.tracking.layouts import get_layout

    name, folder = trained_folders(args)
    body = load_body_model()
    layout = get_layout("blazepose33")
    rows = {
        k: {c: np.asarray(v) for c, v in load_npz(folder / k / "poses.npz").items()}
        for k in ("tracked", "true")
    }

    def joints_of(r):
        def tensor(x):
            return torch.as_tensor(np.asarray(x), dtype=torch.float32)

        return body(betas=tensor(r["shapes"][:, :10]), poses=tensor(r["poses"]).reshape(-1, 72),
                    Rh=tensor(r["Rh"]), Th=tensor(r["Th"])).joints.numpy().astype(np.float64)  # fmt: skip

    fit, true = joints_of(rows["tracked"]), joints_of(rows["true"])
    world = blazepose_world_points(folder / "tracked", rows["tracked"]["frames"])

    def unit(v):
        return v / np.linalg.norm(v, axis=-1, keepdims=True)

    oracle = {}
    for (j, c), _points in CUE_BONES.values():
        t = unit(true[:, c] - true[:, j])
        other = np.stack([flipped_direction(fit[i, j], fit[i, c]) for i in range(len(fit))])
        oracle[(j, c)] = (other * t).sum(-1) > (unit(fit[:, c] - fit[:, j]) * t).sum(-1)
    voted = voted_flips(fit, world, layout)
    decided = {"order-oracle": oracle, "order-voted": voted}
    variants = {
        "tracked": rows["tracked"],
        **{k: with_bones_flipped(rows["tracked"], v) for k, v in decided.items()},
    }
    n = round(0.8 * args.frames)
    true_local = rows["true"]["poses"][:n].reshape(n, 24, 3)[:, 1:]
    report = {"training_frames": n}
    for label, r in variants.items():
        mine = joints_of(r)
        bones = {
            bone: float(np.degrees(np.arccos(np.clip(
                (unit(mine[:n, c] - mine[:n, j]) * unit(true[:n, c] - true[:n, j])).sum(-1), -1, 1))).mean())
            for bone, ((j, c), _points) in CUE_BONES.items()
        }  # fmt: skip
        err = rotation_angles_deg(r["poses"][:n].reshape(n, 24, 3)[:, 1:], true_local).reshape(n, 23)
        groups = {g: float(err[:, [k - 1 for k in js]].mean()) for g, js in JOINT_GROUPS.items()}
        report[label] = {"limb_bones_deg": float(np.mean(list(bones.values()))), "bones": bones,
                         "joint_rotation_deg": float(err.mean()), **groups}  # fmt: skip
        if label != "tracked":
            report[label]["flipped_pct"] = float(
                100 * np.mean([m[:n].mean() for m in decided[label].values()])
            )
            write_pose_variant(folder / label, folder / "tracked", r)
    return report


ORDER_TEST_BONES = ((16, 18), (17, 19), (1, 4), (2, 5))  # upper arms, thighs: ball joints


def ordertest(args) -> dict:
    """The fit's own depth-order test (FitConfig.order_test_bones): the subject's camera (``--runs
    gap`` or ``closeup``) tracked again as ``--format video`` tracks it (unsmoothed, true
    intrinsics), as is and with the test on the upper arms and thighs (:data:`ORDER_TEST_BONES`;
    ``--variant limbs`` adds the forearms and shins); each limb bone's direction and
    depth order and the joints' local rotations against the truth over the training frames. The
    tested poses become the folder ``order-test`` (``order-test-VARIANT``) beside ``decompose``'s
    ``tracked`` (run ``decompose --runs gap-trained`` / ``closeup-trained`` first) for ``decompose
    --steps order-test``, and the default re-tracked the same way (its baseline; it should match
    ``tracked``) the folder ``retracked``."""
    import numpy as np
    import torch

    from stg_node.body import load_body_model
    from stg_node.safe_load import load_npz
    from stg_node.tracking.fitting import FitConfig
    from stg_node.tracking.pipeline import TrackOptions, build_tracker
    from stg_node.tracking.sources import open_source

    name, folder = trained_folders(args)
    if name == "gap":
        data = subject(args.out, f"mixed_{args.size}", num_frames=args.frames, size=args.size)
    else:
        data = closeup_subject(args)
    rows = {
        k: {c: np.asarray(v) for c, v in load_npz(folder / k / "poses.npz").items()}
        for k in ("tracked", "true")
    }
    metadata = json.loads((data / "synth.json").read_text())
    options = TrackOptions(intrinsics=str(intrinsics_file(data)), fps=float(metadata["fps"]), smoothing=False)
    source = open_source(data / "Camera_B1", options.fps)
    frames = [(f.image, f.timestamp) for f in source]
    kept = rows["tracked"]["frames"].astype(int)
    bones = ORDER_TEST_BONES
    if args.variant == "limbs":
        bones = bones + ((18, 20), (19, 21), (4, 7), (5, 8))
    configs = {"retracked": FitConfig(), "order-test": FitConfig(order_test_bones=bones)}
    tracked_rows = {}
    seconds = {}
    for label, config in configs.items():
        started = time.perf_counter()
        tracker, _body = build_tracker(options, source.width, source.height, fit=config)
        out = {k: v.copy() for k, v in rows["tracked"].items()}
        for row, i in enumerate(kept):
            e = tracker.estimate(frames[i][0], frames[i][1])
            out["poses"][row] = np.asarray(e.smpl.poses, np.float64).reshape(72)
            out["Rh"][row], out["Th"][row] = e.smpl.Rh, e.smpl.Th
            out["shapes"][row] = np.asarray(e.smpl.betas)[: out["shapes"].shape[1]]
        tracked_rows[label] = out
        seconds[label] = time.perf_counter() - started
    body = load_body_model()

    def joints_of(r):
        def tensor(x):
            return torch.as_tensor(np.asarray(x), dtype=torch.float32)

        return body(betas=tensor(r["shapes"][:, :10]), poses=tensor(r["poses"]).reshape(-1, 72),
                    Rh=tensor(r["Rh"]), Th=tensor(r["Th"])).joints.numpy().astype(np.float64)  # fmt: skip

    def unit(v):
        return v / np.linalg.norm(v, axis=-1, keepdims=True)

    n = round(0.8 * args.frames)
    true = joints_of(rows["true"])[:n]
    true_local = rows["true"]["poses"][:n].reshape(n, 24, 3)[:, 1:]
    retrack_diff = np.abs(tracked_rows["retracked"]["poses"] - rows["tracked"]["poses"]).max()
    report = {"training_frames": n, "bones_tested": [list(b) for b in bones], "track_seconds": seconds,
              "retracked_max_pose_diff_rad": float(retrack_diff)}  # fmt: skip
    for label, r in (
        ("tracked", rows["tracked"]),
        ("retracked", tracked_rows["retracked"]),
        ("order-test", tracked_rows["order-test"]),
    ):
        mine = joints_of(r)[:n]
        per_bone = {}
        for bone, ((j, c), _points) in CUE_BONES.items():
            d, t = unit(mine[:, c] - mine[:, j]), unit(true[:, c] - true[:, j])
            towards = -(d * unit(mine[:, j])).sum(-1)
            true_towards = -(t * unit(true[:, j])).sum(-1)
            leaning = np.abs(true_towards) > math.sin(math.radians(15))
            wrong = np.sign(towards[leaning]) != np.sign(true_towards[leaning])
            per_bone[bone] = {
                "direction_deg": float(np.degrees(np.arccos(np.clip((d * t).sum(-1), -1, 1))).mean()),
                "order_wrong_pct": float(100 * wrong.mean()) if leaning.any() else float("nan"),
            }
        err = rotation_angles_deg(r["poses"][:n].reshape(n, 24, 3)[:, 1:], true_local).reshape(n, 23)
        report[label] = {
            "limb_bones_deg": float(np.mean([b["direction_deg"] for b in per_bone.values()])),
            "joint_rotation_deg": float(err.mean()),
            **{g: float(err[:, [k - 1 for k in js]].mean()) for g, js in JOINT_GROUPS.items()},
            "bones": per_bone,
        }
    written = "order-test" + (f"-{args.variant}" if args.variant else "")
    write_pose_variant(folder / written, folder / "tracked", tracked_rows["order-test"])
    write_pose_variant(folder / "retracked", folder / "tracked", tracked_rows["retracked"])
    report["folder"] = str(folder / written)
    return report


def twopass(args) -> dict:
    """A fixed-interval smoother for the fit: the training frames of the subject's camera
    (``--runs gap``: the mixed subject; ``closeup``: the dancer) tracked forwards as ``--format
    video`` tracks (unsmoothed, true intrinsics), then backwards with the forward pass's shape
    held, and the two fits averaged per frame (each joint, the global orientation halfway between
    them; the translations' mean): a temporal term that ties each frame to the one before lags a
    fast limb in one direction forwards and in the other backwards. Joint rotations against the
    truth, per group; the three sets of poses in ``--out/twopass``."""
    import cv2
    import numpy as np

    from stg_node.safe_load import load_npy
    from stg_node.tracking.fitting import FitConfig, SmplFitter
    from stg_node.tracking.pipeline import TrackOptions, build_tracker
    from stg_node.tracking.sources import open_source

    name = args.runs or "gap"
    if name == "gap":
        data = subject(args.out, f"mixed_{args.size}", num_frames=args.frames, size=args.size)
    else:
        data = closeup_subject(args)
    metadata = json.loads((data / "synth.json").read_text())
    options = TrackOptions(intrinsics=str(intrinsics_file(data)), fps=float(metadata["fps"]), smoothing=False)
    source = open_source(data / "Camera_B1", options.fps)
    frames = [(f.image, f.timestamp) for f in source][: round(0.8 * args.frames)]

    def track(order, betas=None):
        tracker, body = build_tracker(options, source.width, source.height, fit=FitConfig())
        if betas is not None:  # the backward pass: the forward pass's shape, held
            tracker.fitter = SmplFitter(body, tracker.layout, tracker.intrinsics.K, FitConfig(), betas=betas)
        sign = 1.0 if order[0] < order[-1] else -1.0  # backwards, time still runs forwards
        poses = {}
        for i in order:
            e = tracker.estimate(frames[i][0], sign * frames[i][1])
            poses[i] = np.concatenate(
                [np.asarray(e.smpl.poses, np.float64).reshape(72), e.smpl.Rh, e.smpl.Th]
            )
        return np.stack([poses[i] for i in range(len(frames))]), np.asarray(tracker.fitter.betas)

    forward, betas = track(list(range(len(frames))))
    backward, _ = track(list(range(len(frames)))[::-1], betas)

    def halfway(a, b):
        out = np.empty_like(a)
        for k in range(len(a)):
            Ra, Rb = cv2.Rodrigues(a[k])[0], cv2.Rodrigues(b[k])[0]
            out[k] = cv2.Rodrigues(Ra @ cv2.Rodrigues(0.5 * cv2.Rodrigues(Ra.T @ Rb)[0])[0])[0].ravel()
        return out

    n = len(frames)
    average = np.concatenate(
        [halfway(forward[:, :75].reshape(-1, 3), backward[:, :75].reshape(-1, 3)).reshape(n, 75),
         0.5 * (forward[:, 75:] + backward[:, 75:])], axis=1
    )  # fmt: skip
    folder = args.out / "twopass"
    folder.mkdir(parents=True, exist_ok=True)
    target = folder / f"{name}_{args.size}_s{args.seed}.npz"
    np.savez(target, forward=forward, backward=backward, average=average, betas=betas)

    def true_local(i):
        return np.asarray(load_npy(data / "new_params" / f"{i}.npy")["poses"], np.float64).reshape(24, 3)[1:]

    true = np.stack([true_local(i) for i in range(n)])
    rows = {}
    for label, poses in (("forward", forward), ("backward", backward), ("average", average)):
        err = rotation_angles_deg(poses[:, 3:72].reshape(n, 23, 3), true).reshape(n, 23)
        groups = {g: float(err[:, [j - 1 for j in js]].mean()) for g, js in JOINT_GROUPS.items()}
        rows[label] = {"joint_rotation_deg": float(err.mean()), **groups}
    return {"frames": n, "rows": rows}


JOINT_NAMES = ("pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
               "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
               "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
               "left_wrist", "right_wrist", "left_hand", "right_hand")  # fmt: skip


TWIST_MOTIONS = ("mixed", "dance", "wave", "reach", "walk")


def twist(args) -> dict:
    """The tracker's accuracy on several motions (``--runs``: any of ``stg-synth``'s, default
    :data:`TWIST_MOTIONS`), as ``stg-train --format video`` tracks (the fit's silhouette term on,
    unsmoothed, the training camera's intrinsics): MPJPE / PA-MPJPE, the global orientation, and
    each bone's orientation in the camera's frame against the truth with its twist about the bone
    (:func:`bone_errors`); the mean over the motions beside them."""
    import cv2
    import numpy as np
    import torch

    from stg_node.body import load_body_model
    from stg_node.safe_load import load_npy
    from stg_node.tracking.fitting import FitConfig

    motions = args.runs.split(",") if args.runs else list(TWIST_MOTIONS)
    body = load_body_model()
    parents = body.parents.tolist()
    zeros = torch.zeros(1, 3)
    rest = body(betas=torch.zeros(1, 10), poses=torch.zeros(1, 72), Rh=zeros, Th=zeros).joints[0].numpy()

    def rodrigues(m):
        return cv2.Rodrigues(m)[0]

    rows = {}
    for motion in motions:
        data = subject(
            args.out, f"{motion}_{args.size}", motion=motion, num_frames=args.frames, size=args.size
        )
        poses_out = args.out / "twist" / f"{motion}_{args.size}" / "poses.npz"
        accuracy = track_accuracy(data, FitConfig(), poses_out, smoothing=False)
        tracked = np.load(poses_out)
        n = len(tracked["poses"])
        R = np.asarray(load_npy(data / "annots.npy")["cams"]["R"][0], np.float64)
        names = sorted((data / "Camera_B1").glob("*.png"))[:n]
        params = [load_npy(data / "new_params" / f"{int(p.stem)}.npy") for p in names]
        true_poses = np.stack([np.asarray(p["poses"], np.float64).reshape(24, 3) for p in params])
        true_global = np.stack([
            rodrigues(R @ rodrigues(np.asarray(p["Rh"], np.float64).reshape(3)) @ rodrigues(q[0])).ravel()
            for p, q in zip(params, true_poses, strict=True)
        ])  # fmt: skip
        poses = np.asarray(tracked["poses"], np.float64).reshape(n, 24, 3)
        tracked_global = np.stack([
            rodrigues(rodrigues(np.asarray(rh, np.float64)) @ rodrigues(q[0])).ravel()
            for rh, q in zip(tracked["Rh"], poses, strict=True)
        ])  # fmt: skip
        G_true = camera_frame_rotations(true_global, true_poses[:, 1:], parents)
        G_tracked = camera_frame_rotations(tracked_global, poses[:, 1:], parents)
        rows[motion] = {**accuracy, "bones": bone_errors(G_true, G_tracked, rest)}
        log.info("%s: %s", motion, json.dumps(rows[motion], default=float))
    keys = ("mpjpe_mm", "pa_mpjpe_mm")
    mean = {k: float(np.mean([rows[m][k] for m in motions])) for k in keys}
    mean["global_orientation_deg"] = float(
        np.mean([rows[m]["global_orientation_deg"]["mean"] for m in motions])
    )
    mean["joint_rotation_deg"] = float(np.mean([rows[m]["joint_rotation_deg"]["mean"] for m in motions]))
    mean["bones"] = {
        bone: {
            k: float(np.mean([rows[m]["bones"][bone][k] for m in motions]))
            for k in ("error_deg", "twist_deg")
        }
        for bone in BONES
    }
    rows["mean"] = mean
    return rows


EXPERIMENTS = {
    "gap": gap,
    "sources": sources,
    "exposure": exposure,
    "size": size,
    "focal": focal,
    "framing": framing,
    "fit": fit,
    "refine": refine,
    "chains": chains,
    "errors": errors,
    "twist": twist,
    "closeup": closeup,
    "decompose": decompose,
    "cues": cues,
    "twopass": twopass,
    "order": order,
    "ordertest": ordertest,
}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("experiment", choices=EXPERIMENTS)
    p.add_argument("run", nargs="?", type=Path, default=None, help="framing: the run folder to render")
    p.add_argument("--out", type=Path, default=Path("runs/bench_footage"))
    p.add_argument(
        "--size", type=int, default=512, help="image size of subjects and training (default %(default)s)"
    )
    p.add_argument("--frames", type=int, default=125, help="frames per subject (default %(default)s)")
    p.add_argument(
        "--train-size", type=int, default=None, help="sources: training image size (default: --size)"
    )
    p.add_argument("--close-m", type=float, default=1.9, help="size: the close camera's distance (m)")
    p.add_argument(
        "--closeup-m", type=float, default=2.2, help="closeup: the camera's distance (m; fills the frame)"
    )
    p.add_argument("--far-m", type=float, default=5.0, help="size: the far camera's distance (m)")
    p.add_argument("--figure", type=Path, default=None, help="size: a PNG of one held-out view of every row")
    p.add_argument("--preset", default="fast")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--runs",
        default=None,
        help="gap: which of truth,tracked-before,tracked to train and score here (default: all; "
        "processes running different ones share --out, the last one reports all); fit: any of "
        "accuracy,truth,silhouette,keypoints,unsmoothed (default: accuracy; the trained ones need accuracy's "
        "keypoint-only poses first); exposure: any of steady,jitter,nocorr,steady-nocorr (default: all); "
        "refine: truth and any of REFINE_VARIANTS; size: far,close-fixed,close-gs,close; "
        "chains: true torso, true limbs, true torso world limbs "
        "(names without commas)",
    )
    p.add_argument(
        "--steps", default=None, help="decompose --runs gap-trained: which of " + ",".join(TRAINED_STEPS)
    )
    p.add_argument(
        "--set",
        dest="train_set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="decompose --runs *-trained: a trainer setting for every step's training (repeatable); "
        "needs --variant, which names the runs",
    )
    p.add_argument("--variant", default="", help="decompose --runs *-trained: a name for the --set runs")
    p.add_argument("--json", action="store_true", help="print the results as one JSON object")
    p.add_argument("--iters", type=int, default=None, help="override the iterations (smoke tests)")
    p.add_argument(
        "--focal-frames", type=int, default=150, help="frames of each focal subject (default %(default)s)"
    )
    return p


def main(argv: list[str] | None = None) -> int:
    from stg_node.logs import configure_logging
    from stg_node.threads import configure_threads

    args = build_parser().parse_args(argv)
    if args.experiment == "framing" and args.run is None:
        print("framing needs RUN_DIR", file=sys.stderr)
        return 2
    configure_logging()
    configure_threads(None)
    args.out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    rows = EXPERIMENTS[args.experiment](args)
    result = {
        "experiment": args.experiment,
        "command": "python tools/bench_footage.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "machine": machine(),
        "seconds": time.perf_counter() - started,
        "rows": rows,
    }
    target = args.out / "results" / f"{args.experiment}.json"
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_text(json.dumps(result, indent=1, default=float) + "\n")
    print(json.dumps(result, default=float) if args.json else json.dumps(rows, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
