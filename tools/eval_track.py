#!/usr/bin/env python3
"""Accuracy of the whole tracking chain (video in, SMPL joints out) on the synthetic benchmark.

Generates (or takes) an stg-synth sequence, encodes its training camera's frames as a video,
runs stg-track's pipeline on it with the benchmark's intrinsics, and compares the tracked SMPL
joints with the ground truth in that camera's frame:

    MPJPE      mean per-joint error after aligning the pelvis (mm)
    PA-MPJPE   the same after a per-frame similarity (Procrustes) alignment (mm)
    accel      jitter: mean error of the joints' second differences (mm/frame^2)
    mask IoU   the tracker's person masks against the rendered ones

    python tools/eval_track.py [--data DIR | --frames 300 --size 512 --seed 0 --motion mixed]
                               [--no-smoothing] [--image-folder] [--json OUT.json]
    python tools/eval_track.py --rig 4 [...]     several cameras (docs/RIGS.md): N of a 23-camera ring
                                                 (ZJU-MoCap's layout), tracked together in the world frame

Exit codes: 0 done, 1 failed (missing network files, ...), 2 bad usage.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's stg_node first
sys.path.insert(0, str(Path(__file__).resolve().parent))


def main(argv: list[str] | None = None) -> int:
    from stg_node.logs import configure_logging
    from stg_node.threads import configure_threads

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=None, help="an existing stg-synth folder")
    parser.add_argument("--frames", type=int, default=300, help="frames to generate (default %(default)s)")
    parser.add_argument("--size", type=int, default=512, help="image size to generate (default %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="seed to generate with (default %(default)s)")
    parser.add_argument("--motion", default="mixed", help="motion to generate (default %(default)s)")
    parser.add_argument("--no-smoothing", action="store_true", help="report the raw per-frame fits")
    parser.add_argument("--image-folder", action="store_true", help="track the PNG frames, not a video")
    parser.add_argument("--detector", default="blazepose", help="keypoint detector (default %(default)s)")
    parser.add_argument("--pose-model", default=None, help="network file or folder for the detector")
    parser.add_argument("--mask-method", default=None, help="mask method (default: the detector's)")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures as JSON")
    parser.add_argument(
        "--rig",
        type=int,
        default=0,
        metavar="N",
        help="track N cameras spread around a 23-camera ring together",
    )
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument("--threads", default=None, help="CPU threads (default: STG_THREADS or 1)")
    args = parser.parse_args(argv)
    configure_logging()
    threads = configure_threads(args.threads)

    from stg_node.data.synth import SynthConfig, generate
    from stg_node.tracking.evaluation import evaluate_synth
    from stg_node.tracking.model_files import PoseModelError
    from stg_node.tracking.pipeline import TrackOptions
    from stg_node.tracking.runtime import RunnerError

    options = TrackOptions(
        detector=args.detector,
        pose_model=args.pose_model,
        mask=args.mask_method,
        smoothing=not args.no_smoothing,
    )
    if args.rig:
        from eval_track_rig import run_rig

        return run_rig(args, options, threads)
    with tempfile.TemporaryDirectory(prefix="eval_track_") as tmp:
        data = args.data
        if data is None:
            data = Path(tmp) / "synth"
            config = SynthConfig(
                out=data,
                seed=args.seed,
                num_frames=args.frames,
                size=args.size,
                motion=args.motion,
                num_novel_views=0,
            )
            try:
                config.validate()
            except ValueError as err:
                parser.error(str(err))
            generate(config, progress=not args.no_progress)
        try:
            report = evaluate_synth(
                data, options, as_video=not args.image_folder, progress=not args.no_progress, threads=threads
            )
        except (PoseModelError, RunnerError, ValueError, OSError) as err:
            print(f"eval_track: {err}", file=sys.stderr)
            return 1
    source = (
        str(args.data)
        if args.data
        else f"stg-synth seed {args.seed}, {args.frames} frames, {args.size} px, {args.motion}"
    )
    print(
        f"tracking chain on {source} ({'image folder' if args.image_folder else 'MJPG video'}, "
        f"smoothing {'off' if args.no_smoothing else 'on'}, detector {args.detector})"
    )
    print(f"  frames          {report.frames}")
    print(f"  MPJPE           {report.mpjpe_mm:.1f} mm (median {report.median_mpjpe_mm:.1f})")
    print(f"  PA-MPJPE        {report.pa_mpjpe_mm:.1f} mm")
    print(f"  accel error     {report.accel_mm:.2f} mm/frame^2")
    print(f"  mask IoU        {report.mask_iou:.3f}")
    print(f"  confident       {100 * report.confident_fraction:.0f} % of frames (confidence >= 0.5)")
    print(
        f"  tracking speed  {report.fps:.1f} frames/s end to end ({threads} thread(s), "
        f"{platform.processor() or platform.machine()})"
    )
    if args.json is not None:
        args.json.write_text(
            json.dumps({"source": source, **report.__dict__, "fps": report.fps}, indent=2) + "\n"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
