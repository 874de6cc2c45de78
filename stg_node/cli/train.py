"""``stg-train``: train an STG-Avatar on a monocular video with per-frame SMPL parameters.

    stg-train --data DIR --format zju|synthetic|thuman|folder|video --out RUN_DIR
              [--preset fast|balanced|quality] [--smpl-model FILE] [--train-frames A:B]
              [--train-camera NAME] [--iters N]
              [--backend auto|cpu|cuda|torch] [--threads T] [--seed S] [--resume]
    stg-train --data VIDEO --format video --out RUN_DIR [--intrinsics FILE.json | --fov DEG] [...]
    stg-train --data DIR --format video --calibration rig.json --out RUN_DIR [--train-cameras A,B]  (a rig)

``--format video`` takes a video file (or a folder of images): it is tracked first (stg-track's
SMPL fit and person masks, cached by content; stg_node/avatar/video.py) into the folder format
under ``RUN_DIR/video_data``, then trained like any dataset, so a phone video becomes an avatar
with ``stg-train`` alone.

The run folder layout is in stg_node/avatar/run.py; docs/AVATAR.md explains the method and
every preset. Exit codes (docs/CLI.md): 0 trained, 1 the training failed (bad data), 2 bad usage,
130 stopped by Ctrl-C/SIGTERM after a final checkpoint (continue with --resume).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

from stg_node.cli.runner import CommandFailed, UsageError, add_log_level_option, run_main
from stg_node.signals import StopSignals
from stg_node.threads import configure_threads

log = logging.getLogger("stg_node.cli.train")


def build_parser() -> argparse.ArgumentParser:
    from stg_node.avatar.data_spec import FORMATS
    from stg_node.avatar.presets import PRESETS

    p = argparse.ArgumentParser(
        prog="stg-train",
        description="Train an STG-Avatar (SMPL + LBS + Spacetime Gaussians + flow-guided densification) "
        "from a monocular video with SMPL parameters.",
    )
    p.add_argument("--data", required=True, help="dataset folder (or, with --format video, a video file)")
    p.add_argument("--format", required=True, choices=FORMATS, help="dataset layout")
    p.add_argument("--out", required=True, help="run folder (created); holds checkpoints, logs, the model")
    p.add_argument(
        "--preset", default="balanced", choices=PRESETS, help="speed/quality preset (default %(default)s)"
    )
    p.add_argument(
        "--smpl-model",
        default=None,
        help="SMPL-format body file the parameters refer to (default: the open body)",
    )
    p.add_argument(
        "--train-frames",
        default=None,
        help="training frame range A:B (default: the dataset's protocol; a video: its own frame numbers)",
    )
    p.add_argument(
        "--train-camera", default=None, help="training camera name (default: the protocol's, camera 1)"
    )
    p.add_argument(
        "--train-cameras",
        default=None,
        metavar="A,B,...",
        help="several training cameras (a rig; the novel views are then every other camera): docs/RIGS.md",
    )
    p.add_argument("--iters", type=int, default=None, help="training iterations (default: the preset's)")
    p.add_argument(
        "--checkpoint-every",
        type=int,
        default=None,
        help="iterations between checkpoints (default: the preset's)",
    )
    p.add_argument(
        "--backend", default="auto", choices=("auto", "cpu", "cuda", "torch"), help="splatting backend"
    )
    p.add_argument(
        "--device",
        default=None,
        help="torch device (default: cuda when --backend cuda/auto finds one, else cpu)",
    )
    p.add_argument(
        "--size", type=int, default=512, help="image size the frames are loaded at (default %(default)s)"
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="change one setting of the preset, e.g. model.spacetime=false or model.max_gaussians=60000 "
        "(repeatable; names in stg_node/avatar/config.py; a new run only)",
    )
    p.add_argument("--threads", default=None, help="CPU threads (default: STG_THREADS or 1)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default %(default)s)")
    p.add_argument("--resume", action="store_true", help="continue from RUN_DIR's last checkpoint")
    camera = p.add_mutually_exclusive_group()
    camera.add_argument(
        "--intrinsics",
        default=None,
        metavar="FILE.json",
        help='--format video: the camera, JSON with "K" (3x3) and optionally "dist" (OpenCV)',
    )
    camera.add_argument(
        "--fov",
        type=float,
        default=None,
        metavar="DEG",
        help="--format video: horizontal field of view without a calibration (default 65)",
    )
    p.add_argument(
        "--calibration",
        default=None,
        metavar="RIG.json",
        help="--format video of a rig: its rig.json; --data holds one recording per camera (docs/RIGS.md)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_log_level_option(p)
    return p


def main(argv: list[str] | None = None) -> int:
    from stg_node.avatar.snapshot import SnapshotError
    from stg_node.body import BodyModelError
    from stg_node.data.errors import DatasetError
    from stg_node.tracking.model_files import PoseModelError
    from stg_node.tracking.runtime import RunnerError

    expected = (DatasetError, BodyModelError, SnapshotError, PoseModelError, RunnerError)
    return run_main(build_parser(), run, argv, expected=expected)


def run(args: argparse.Namespace) -> int:
    from stg_node.avatar.data_spec import parse_frame_range

    if args.iters is not None and args.iters < 1:
        raise UsageError("--iters must be >= 1")
    if args.checkpoint_every is not None and args.checkpoint_every < 1:
        raise UsageError("--checkpoint-every must be >= 1")
    try:
        frames = parse_frame_range(args.train_frames)
    except ValueError as exc:
        raise UsageError(str(exc)) from exc
    train_cameras = rig_cameras_option(args)
    if args.format != "video" and (args.intrinsics is not None or args.fov is not None):
        raise UsageError("--intrinsics and --fov describe the camera of a video: only with --format video")
    if args.fov is not None and not 1.0 <= args.fov <= 170.0:
        raise UsageError(f"--fov must be between 1 and 170 degrees, got {args.fov}")
    if args.calibration is not None and (args.format != "video" or args.intrinsics or args.fov):
        raise UsageError(
            "--calibration (a rig's rig.json) goes with --format video, without --intrinsics/--fov"
        )
    if args.calibration is not None and not Path(args.calibration).is_file():
        raise UsageError(f"--calibration {args.calibration} does not exist")
    if args.format == "video" and args.calibration is None and not Path(args.data).exists():
        raise CommandFailed(f"--data {args.data}: no such video file or image folder")
    if args.format != "video" and not Path(args.data).is_dir():
        raise CommandFailed(f"--data {args.data}: no such folder")
    from stg_node.avatar.config import apply_settings
    from stg_node.avatar.presets import preset
    from stg_node.avatar.run import RunDir

    base = preset(args.preset)
    if args.format == "video":  # a tracker's poses: refined harder, kept smooth (avatar/pose_refine.py)
        from stg_node.avatar.exposure import for_footage
        from stg_node.avatar.pose_refine import refinement_for

        base = for_footage(refinement_for(base, "tracked"))  # a phone's exposure drifts
    try:
        args.config = apply_settings(base, args.set)
    except ValueError as exc:
        raise UsageError(f"--set: {exc}") from exc
    if args.set and args.resume and RunDir(Path(args.out)).checkpoint.is_file():
        raise UsageError(f"--set changes a new run's settings; {args.out} resumes with its own (config.json)")
    args.train_cameras_tuple = train_cameras
    configure_threads(args.threads)
    with StopSignals() as stop:
        return _train(args, frames, stop)


def rig_cameras_option(args) -> tuple[str, ...] | None:
    """``--train-cameras A,B`` as a tuple (None without it), checked against ``--train-camera``."""
    if args.train_cameras is None:
        return None
    if args.train_camera is not None:
        raise UsageError("give --train-camera (one camera) or --train-cameras (several), not both")
    names = tuple(n.strip() for n in args.train_cameras.split(","))
    if not all(names) or len(set(names)) != len(names):
        raise UsageError(
            f"--train-cameras must be distinct names separated by commas, got {args.train_cameras!r}"
        )
    return names


def _device(args) -> str:
    if args.device:
        return args.device
    import torch

    if args.backend in ("cuda", "auto") and torch.cuda.is_available():
        return "cuda"
    return "cpu"


def _train(args, frames, stop: StopSignals) -> int:
    from stg_node.avatar.data_spec import DataSpec
    from stg_node.avatar.run import RunDir, write_json
    from stg_node.avatar.trainer import Trainer
    from stg_node.avatar.training_log import TrainingLog
    from stg_node.data.flow import FlowCache
    from stg_node.progress import progress

    wall_start = time.perf_counter()
    run = RunDir(Path(args.out))
    data_root = args.data
    if args.format == "video" and args.calibration is not None:
        from stg_node.avatar.rig_video import prepare_rig_videos
        from stg_node.calibration.rig import read_rig

        data_root = str(
            prepare_rig_videos(
                args.data,
                run.path / "video_data",
                args.calibration,
                smpl_model=args.smpl_model,
                progress=not args.no_progress,
            )
        )
        if args.train_cameras_tuple is None:  # every camera of the rig trains
            args.train_cameras_tuple = tuple(read_rig(args.calibration).names)
    elif args.format == "video":
        from stg_node.avatar.video import prepare_video

        data_root = str(
            prepare_video(
                args.data,
                run.path / "video_data",
                smpl_model=args.smpl_model,
                intrinsics=args.intrinsics,
                fov_deg=args.fov,
                progress=not args.no_progress,
                preview=run.path / "fit_preview.mp4",
            )
        )
    spec = DataSpec(
        str(Path(data_root).resolve()),
        args.format,
        frames,
        args.train_camera,
        args.size,
        args.train_cameras_tuple,
    )
    device = _device(args)
    flow_cache = FlowCache(run.flow_cache)
    resumed = False
    if args.resume and run.checkpoint.is_file():
        trainer = Trainer.load(
            run.checkpoint,
            body_model=args.smpl_model,
            device=device,
            backend=args.backend,
            flow_cache=flow_cache,
        )
        if args.iters is not None and args.iters != trainer.config.iterations:
            trainer.config = trainer.config.replace(iterations=args.iters)
        resumed = True
        log.info("resuming %s at iteration %d", run.checkpoint, trainer.iteration)
    else:
        if args.resume:
            log.warning("--resume: no checkpoint in %s yet; starting from scratch", run.path)
        config = args.config
        if args.iters is not None:
            config = config.replace(iterations=args.iters)
        config = _scaled_budget(args, config, spec)
        trainer = Trainer(
            config,
            args.smpl_model,
            device=device,
            backend=args.backend,
            seed=args.seed,
            flow_cache=flow_cache,
        )
    if args.checkpoint_every is not None:
        trainer.config = trainer.config.replace(checkpoint_every=args.checkpoint_every)
    config = trainer.config
    run.write_config(
        {
            "config": config.to_dict(),
            "data": spec.to_dict(),
            "body_model": args.smpl_model or "open",
            "seed": trainer.seed,
            "backend": args.backend,
            "device": device,
            "versions": _versions(),
        }
    )
    dataset = spec.open("train")
    trainer.add_frames(progress(dataset, desc="loading frames", unit="frame", enabled=not args.no_progress))
    log.info(
        "%d training frames (%s), %d with optical flow",
        len(trainer.store),
        spec.format,
        sum(1 for f in trainer.store.frames if f.flow is not None),
    )
    tlog = TrainingLog(run.log, append=resumed)
    bar = progress(desc="training", unit="it", total=config.iterations, enabled=not args.no_progress)
    bar.update(trainer.iteration)
    last_save = trainer.iteration
    while trainer.iteration < config.iterations and not stop.requested:
        result = trainer.step()
        bar.update(1)
        if result.iteration % config.log_every == 0 or result.skipped:
            tlog.write(result)
            bar.set_postfix(
                loss=f"{result.loss:.4f}",
                psnr=f"{result.psnr:.2f}",
                gaussians=result.num_gaussians,
                refresh=False,
            )
        if result.iteration - last_save >= config.checkpoint_every:
            trainer.save(run.checkpoint)
            last_save = result.iteration
    bar.close()
    trainer.save(run.checkpoint)
    finished = trainer.iteration >= config.iterations
    from stg_node.avatar.snapshot import write_snapshot_file

    if finished:
        write_snapshot_file(run.avatar, trainer.snapshot())
    stats = trainer.stats()
    summary = {
        "finished": finished,
        "iterations": trainer.iteration,
        "train_seconds": trainer.train_seconds,
        "wall_seconds_this_session": time.perf_counter() - wall_start,
        "skipped_steps": trainer.skipped_steps,
        "frames": len(trainer.store),
        "preset": config.preset,
        "budget": getattr(args, "budget", None),
        "tracking": _tracking_report(run),
        **stats,
        "densify": trainer.densify_counts,
        "nonrigid": trainer.nonrigid_report(),
        "normal_sign": trainer.normal_sign_report(),
    }
    write_json(run.summary, summary)
    tlog.close()
    tlog.plot(run.curves)
    print(json.dumps(summary))
    if not finished:
        log.warning(
            "stopped at iteration %d of %d; continue with --resume", trainer.iteration, config.iterations
        )
        return 130
    return 0


def _tracking_report(run):
    """What ``--format video``'s tracking kept, skipped (and why) and its camera; None otherwise."""
    from stg_node.tracking.pipeline import TRACKING_REPORT

    path = run.path / "video_data" / TRACKING_REPORT
    return json.loads(path.read_text()) if path.is_file() else None


def _scaled_budget(args, config, spec):
    """The preset's budget scaled with the person's size in pixels (stg_node/avatar/budget.py); what
    the user set (``--set``, ``--iters``) stays as given."""
    from stg_node.avatar.budget import SCALED, sample_masks, scale_budget

    fixed = tuple(key for key in SCALED if any(item.split("=", 1)[0].strip() == key for item in args.set))
    if args.iters is not None:
        fixed += ("iterations",)
    config, budget = scale_budget(config, sample_masks(spec.open("train")), fixed=fixed)
    log.info("%s", budget.describe())
    args.budget = budget.as_dict()
    return config


def _versions() -> dict:
    import platform
    from importlib import metadata

    import torch

    try:
        ours = metadata.version("stg_node")
    except metadata.PackageNotFoundError:
        ours = "unknown"
    return {"stg_node": ours, "python": platform.python_version(), "torch": torch.__version__}


if __name__ == "__main__":
    sys.exit(main())
