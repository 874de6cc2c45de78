"""``stg-track``: SMPL pose and person mask per frame of a video or an image folder -> POSES.npz.

    stg-track INPUT --out POSES.npz [--intrinsics FILE.json | --fov DEG] [--smpl-model FILE] [--masks DIR]
              [--preview fit.mp4]
    stg-track CAM1 CAM2 ... --calibration rig.json --out POSES.npz [--cameras NAME,...]  (docs/RIGS.md)

Without --intrinsics or --fov the focal length is estimated from the footage and the command
says how sure it is (an unsure estimate keeps the default 65 degrees). --preview writes the input
with the fitted SMPL mesh, the person mask and each frame's confidence drawn over it. The last
lines say how many frames were skipped (confidence below 0.5) and why.

Exit codes as every command (docs/CLI.md): 0 done, 1 the tracking failed (unreadable input,
missing network files, ...), 2 bad usage, 130 interrupted (POSES.npz is then not written).
See docs/TRACKING.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from stg_node.cli.runner import UsageError, add_log_level_option, run_main
from stg_node.threads import configure_threads


def build_parser() -> argparse.ArgumentParser:
    from stg_node.tracking.camera import DEFAULT_FOV_DEG
    from stg_node.tracking.detectors import DETECTORS
    from stg_node.tracking.masks import MASK_METHODS

    parser = argparse.ArgumentParser(
        prog="stg-track",
        description="Estimate the SMPL pose, shape and a person mask for every frame of a video file or an "
        "image folder, in the camera's frame, and write them to POSES.npz.",
    )
    parser.add_argument(
        "input",
        nargs="+",
        type=Path,
        help="a video file or a folder of images; with --calibration, one per camera of the rig",
    )
    parser.add_argument("--out", required=True, type=Path, help="the POSES.npz to write")
    camera = parser.add_mutually_exclusive_group()
    camera.add_argument(
        "--intrinsics", type=Path, default=None, help='JSON with "K" (3x3) and optionally "dist" (OpenCV)'
    )
    camera.add_argument(
        "--fov",
        type=float,
        default=None,
        metavar="DEG",
        help="horizontal field of view without a calibration (default: estimated from the footage, "
        f"{DEFAULT_FOV_DEG:g} when it cannot be)",
    )
    parser.add_argument(
        "--smpl-model", default=None, help="SMPL .pkl/.npz file or folder (default: the open body that ships)"
    )
    parser.add_argument(
        "--masks", type=Path, default=None, metavar="DIR", help="also write masks DIR/000000.png ..."
    )
    parser.add_argument(
        "--preview",
        type=Path,
        default=None,
        metavar="FILE.mp4",
        help="also write the input with the fitted mesh, the mask and the confidence drawn over it",
    )
    parser.add_argument(
        "--detector", choices=DETECTORS, default="blazepose", help="keypoint network (default %(default)s)"
    )
    parser.add_argument(
        "--pose-model",
        default=None,
        metavar="PATH",
        help="ONNX file for --detector onnx; for blazepose a folder holding its two .tflite files",
    )
    parser.add_argument(
        "--mask-method",
        choices=[m for m in MASK_METHODS if m != "depth"],
        default=None,
        help="person mask: segmentation (blazepose's, default), plate, mog2, knn, none",
    )
    parser.add_argument(
        "--plate", type=Path, default=None, help="image of the empty scene for --mask-method plate"
    )
    parser.add_argument("--fps", type=float, default=None, help="frame rate of an image folder (default 30)")
    parser.add_argument(
        "--max-side",
        type=int,
        default=512,
        help="detect on frames scaled to this long side (default %(default)s)",
    )
    parser.add_argument("--no-smoothing", action="store_true", help="no One-Euro smoothing of the parameters")
    from stg_node.cli.track_rig import add_rig_options

    add_rig_options(parser)
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--threads", default=None, help="CPU threads (default: STG_THREADS or 1)")
    add_log_level_option(parser)
    return parser


def run(args: argparse.Namespace) -> int:
    try:
        threads = configure_threads(args.threads)
    except ValueError as exc:
        raise UsageError(str(exc)) from exc
    if args.calibration is not None or len(args.input) > 1:
        from stg_node.cli.track_rig import run_rig

        return run_rig(args, threads)
    args.input = args.input[0]
    if not args.input.exists():
        raise UsageError(f"INPUT {args.input} does not exist (a video file or a folder of images)")
    if args.out.suffix != ".npz":
        raise UsageError(f"--out must name a .npz file, got {args.out}")
    if args.mask_method == "plate" and args.plate is None:
        raise UsageError("--mask-method plate needs --plate FILE (an image of the empty scene)")
    if args.detector == "onnx" and args.pose_model is None:
        raise UsageError("--detector onnx needs --pose-model FILE.onnx")
    if args.fps is not None and not args.fps > 0:
        raise UsageError(f"--fps must be positive, got {args.fps}")
    if args.preview is not None and args.preview.suffix.lower() != ".mp4":
        raise UsageError(f"--preview must name an .mp4 file, got {args.preview}")
    if args.max_side != 0 and args.max_side < 64:
        raise UsageError(f"--max-side must be 0 (native) or at least 64, got {args.max_side}")

    from stg_node.tracking.pipeline import TrackOptions, track_to_file

    options = TrackOptions(
        intrinsics=None if args.intrinsics is None else str(args.intrinsics),
        smpl_model=args.smpl_model,
        detector=args.detector,
        pose_model=args.pose_model,
        mask=args.mask_method,
        plate=None if args.plate is None else str(args.plate),
        fps=args.fps,
        max_side=args.max_side,
        smoothing=not args.no_smoothing,
        **({} if args.fov is None else {"fov_deg": args.fov}),
    )
    summary = track_to_file(
        args.input,
        args.out,
        options,
        masks_dir=args.masks,
        preview=args.preview,
        progress=not args.no_progress,
        threads=threads,
    )
    print(
        f"wrote {summary.out}: {summary.frames} frames, {summary.confident_frames} confident "
        f"(mean confidence {summary.mean_confidence:.2f}) in {summary.seconds:.1f} s"
    )
    print(summary.describe_skipped())
    if summary.camera:
        print(summary.camera)
    if args.preview is not None:
        print(f"fit preview: {args.preview}")
    return 0


def main(argv: list[str] | None = None) -> int:
    from stg_node.tracking.model_files import PoseModelError
    from stg_node.tracking.runtime import RunnerError

    # Missing or unloadable network files are the user's situation (the message names the fix).
    return run_main(build_parser(), run, argv, expected=(PoseModelError, RunnerError))


if __name__ == "__main__":
    sys.exit(main())
