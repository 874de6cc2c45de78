"""``stg-train``: train an STG-Avatar on a monocular video with per-frame SMPL parameters.

    stg-train --data DIR --format zju|synthetic|thuman|video --out RUN_DIR [--preset fast|balanced|quality]
              [--smpl-model FILE] [--train-frames A:B] [--train-camera NAME] [--iters N]
              [--backend auto|cpu|cuda|torch] [--threads T] [--seed S] [--resume]

The run folder layout is in stg_node/avatar/run.py; docs/AVATAR.md explains the method and
every preset. Exit codes: 0 trained, 1 the training failed (bad data, a diverged model), 2 bad usage.
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import time

from stg_node.logs import configure_logging
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
    p.add_argument("--preset", default="balanced", choices=PRESETS, help="speed/quality preset (default %(default)s)")
    p.add_argument("--smpl-model", default=None, help="SMPL-format body file the parameters refer to (default: the open body)")
    p.add_argument("--train-frames", default=None, help="training frame range A:B (default: the dataset's protocol)")
    p.add_argument("--train-camera", default=None, help="training camera name (default: the protocol's, camera 1)")
    p.add_argument("--iters", type=int, default=None, help="training iterations (default: the preset's)")
    p.add_argument("--backend", default="auto", choices=("auto", "cpu", "cuda", "torch"), help="splatting backend")
    p.add_argument("--device", default=None, help="torch device (default: cuda when --backend cuda/auto finds one, else cpu)")
    p.add_argument("--size", type=int, default=512, help="image size the frames are loaded at (default %(default)s)")
    p.add_argument("--threads", default=None, help="CPU threads (default: STG_THREADS or 1)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default %(default)s)")
    p.add_argument("--resume", action="store_true", help="continue from RUN_DIR's last checkpoint")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--log-level", default=None, help="log level (default: STG_LOG_LEVEL or INFO)")
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    configure_logging(args.log_level)
    if args.iters is not None and args.iters < 1:
        parser.error("--iters must be >= 1")
    try:
        from stg_node.avatar.data_spec import parse_frame_range

        frames = parse_frame_range(args.train_frames)
    except ValueError as exc:
        parser.error(str(exc))
    configure_threads(args.threads)
    stop = _install_stop_handlers()
    try:
        return _train(args, frames, stop)
    except KeyboardInterrupt:
        log.warning("interrupted")
        return 130
    except Exception as exc:  # reported once, without a traceback for the expected kinds
        from stg_node.avatar.snapshot import SnapshotError
        from stg_node.body import BodyModelError
        from stg_node.data.errors import DatasetError

        if isinstance(exc, (DatasetError, BodyModelError, SnapshotError, FileNotFoundError, ValueError)):
            log.error("%s", exc)
        else:
            log.exception("training failed")
        return 1


def _install_stop_handlers():
    """SIGINT/SIGTERM end the run after the current step, with a final checkpoint."""
    state = {"stop": False}

    def handler(signum, _frame):
        if state["stop"]:  # second signal: leave now
            raise KeyboardInterrupt
        state["stop"] = True
        log.warning("%s received: stopping after this step (checkpoint kept); again to abort", signal.Signals(signum).name)

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return state


def _device(args) -> str:
    if args.device:
        return args.device
    import torch

    if args.backend in ("cuda", "auto") and torch.cuda.is_available():
        return "cuda"
    return "cpu"


def _train(args, frames, stop) -> int:
    from pathlib import Path

    from stg_node.avatar.data_spec import DataSpec
    from stg_node.avatar.presets import preset
    from stg_node.avatar.run import RunDir, write_json
    from stg_node.avatar.trainer import Trainer
    from stg_node.avatar.training_log import TrainingLog
    from stg_node.data.flow import FlowCache
    from stg_node.progress import progress

    wall_start = time.perf_counter()
    run = RunDir(Path(args.out))
    data_root = args.data
    if args.format == "video":
        from stg_node.avatar.video import prepare_video

        data_root = str(prepare_video(args.data, run.path / "video_data", smpl_model=args.smpl_model))
    spec = DataSpec(str(Path(data_root).resolve()), args.format, frames, args.train_camera, args.size)
    device = _device(args)
    flow_cache = FlowCache(run.flow_cache)
    resumed = False
    if args.resume and run.checkpoint.is_file():
        trainer = Trainer.load(run.checkpoint, body_model=args.smpl_model, device=device, backend=args.backend,
                               flow_cache=flow_cache)
        if args.iters is not None and args.iters != trainer.config.iterations:
            trainer.config = trainer.config.replace(iterations=args.iters)
        resumed = True
        log.info("resuming %s at iteration %d", run.checkpoint, trainer.iteration)
    else:
        if args.resume:
            log.warning("--resume: no checkpoint in %s yet; starting from scratch", run.path)
        config = preset(args.preset)
        if args.iters is not None:
            config = config.replace(iterations=args.iters)
        trainer = Trainer(config, args.smpl_model, device=device, backend=args.backend, seed=args.seed,
                          flow_cache=flow_cache)
    config = trainer.config
    run.write_config({
        "config": config.to_dict(),
        "data": spec.to_dict(),
        "body_model": args.smpl_model or "open",
        "seed": trainer.seed,
        "backend": args.backend,
        "device": device,
        "versions": _versions(),
    })
    dataset = spec.open("train")
    trainer.add_frames(progress(dataset, desc="loading frames", unit="frame", enabled=not args.no_progress))
    log.info("%d training frames (%s), %d with optical flow", len(trainer.store), spec.format,
             sum(1 for f in trainer.store.frames if f.flow is not None))
    tlog = TrainingLog(run.log, append=resumed)
    bar = progress(desc="training", unit="it", total=config.iterations, enabled=not args.no_progress)
    bar.update(trainer.iteration)
    last_save = trainer.iteration
    while trainer.iteration < config.iterations and not stop["stop"]:
        result = trainer.step()
        bar.update(1)
        if result.iteration % config.log_every == 0 or result.skipped:
            tlog.write(result)
            bar.set_postfix(loss=f"{result.loss:.4f}", psnr=f"{result.psnr:.2f}", gaussians=result.num_gaussians,
                            refresh=False)
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
        **stats,
        "densify": dict(trainer.densifier.counts),
    }
    write_json(run.summary, summary)
    tlog.close()
    tlog.plot(run.curves)
    print(json.dumps(summary))
    if not finished:
        log.warning("stopped at iteration %d of %d; continue with --resume", trainer.iteration, config.iterations)
    return 0


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
