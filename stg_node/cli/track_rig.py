"""``stg-track`` for a rig: one input per camera, ``--calibration rig.json`` (docs/RIGS.md).

    stg-track CAM1.mp4 CAM2.mp4 ... --calibration rig.json --out POSES.npz [--cameras NAME,...]
              [--masks DIR] [--max-skew-ms MS] [the single-camera options that apply]

The inputs are in the order of rig.json's cameras, or ``--cameras`` names each input's camera.
Frames are matched by time stamp (unsynchronised inputs: exit 1, the message says by how much
they drift); the SMPL parameters are in the rig's world frame; ``--masks DIR`` writes
``DIR/NAME/000000.png`` per camera.
"""

from __future__ import annotations

import argparse

from stg_node.cli.runner import UsageError


def add_rig_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--calibration",
        type=str,
        default=None,
        metavar="RIG.json",
        help="several cameras: their rig.json (stg-calibrate); the inputs are one per camera",
    )
    parser.add_argument(
        "--cameras",
        default=None,
        metavar="NAME,...",
        help="with --calibration: the rig camera of each input (default: rig.json's order)",
    )
    parser.add_argument(
        "--max-skew-ms",
        type=float,
        default=None,
        help="with --calibration: frames of one instant lie this close in time (default half a frame)",
    )


def run_rig(args: argparse.Namespace, threads: int | None) -> int:
    from pathlib import Path

    if args.calibration is None:
        raise UsageError(
            f"{len(args.input)} inputs: several cameras need --calibration rig.json (stg-calibrate)"
        )
    if args.intrinsics is not None or args.fov is not None:
        raise UsageError("--intrinsics and --fov describe one camera; a rig's cameras are in --calibration")
    if not Path(args.calibration).is_file():
        raise UsageError(f"--calibration {args.calibration} does not exist")
    missing = [str(p) for p in args.input if not p.exists()]
    if missing:
        raise UsageError(f"no such input: {', '.join(missing)}")
    if args.out.suffix != ".npz":
        raise UsageError(f"--out must name a .npz file, got {args.out}")
    if args.max_skew_ms is not None and not args.max_skew_ms > 0:
        raise UsageError(f"--max-skew-ms must be positive, got {args.max_skew_ms}")
    if args.detector == "onnx" and args.pose_model is None:
        raise UsageError("--detector onnx needs --pose-model FILE.onnx")
    cameras = [n.strip() for n in args.cameras.split(",")] if args.cameras else None

    from stg_node.tracking.pipeline import TrackOptions
    from stg_node.tracking.rig_pipeline import track_rig_to_file

    options = TrackOptions(
        smpl_model=args.smpl_model,
        detector=args.detector,
        pose_model=args.pose_model,
        mask=args.mask_method,
        plate=None if args.plate is None else str(args.plate),
        fps=args.fps,
        max_side=args.max_side,
        smoothing=not args.no_smoothing,
    )
    summary = track_rig_to_file(
        args.input,
        args.calibration,
        args.out,
        options,
        cameras=cameras,
        masks_dir=args.masks,
        max_skew_s=None if args.max_skew_ms is None else args.max_skew_ms / 1e3,
        progress=not args.no_progress,
        threads=threads,
    )
    print(
        f"wrote {summary.out}: {summary.frames} instants of {len(args.input)} cameras, "
        f"{summary.confident_frames} confident (mean confidence {summary.mean_confidence:.2f}) in "
        f"{summary.seconds:.1f} s; parameters in the rig's world frame"
    )
    return 0
