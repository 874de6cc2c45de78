"""tools/eval_track.py --rig N: the multi-view tracking chain on a synthetic rig (docs/RIGS.md).

Generates (or takes, ``--data``) an stg-synth subject in ZJU-MoCap's layout, 23 cameras on a ring,
of which N spread around it render every frame (``--train-cameras``), writes those N cameras'
frames as MJPG videos and their calibration as a rig.json, tracks them together
(``stg-track ... --calibration rig.json``), and compares the SMPL joints with the truth in the
world frame: MPJPE (pelvis-aligned, as the monocular figure), PA-MPJPE, the pelvis's own error.
"""

from __future__ import annotations

import json
import platform
import sys
import tempfile
from pathlib import Path

RING = 23


def spread(count: int, total: int = RING) -> list[str]:
    return [str(round(i * total / count) + 1) for i in range(count)]


def run_rig(args, options, threads) -> int:
    from stg_node.data.synth import SynthConfig, generate
    from stg_node.tracking.model_files import PoseModelError
    from stg_node.tracking.rig_evaluation import evaluate_synth_rig
    from stg_node.tracking.runtime import RunnerError

    cameras = spread(args.rig)
    with tempfile.TemporaryDirectory(prefix="eval_track_rig_") as tmp:
        data = args.data
        if data is None:
            data = Path(tmp) / "synth"
            config = SynthConfig(
                out=data,
                seed=args.seed,
                num_frames=args.frames,
                size=args.size,
                motion=args.motion,
                num_novel_views=RING - 1,
                view_every=max(args.frames, 1),
                train_cameras=tuple(int(c) - 1 for c in cameras),
            )
            config.validate()
            generate(config, progress=not args.no_progress)
        try:
            report = evaluate_synth_rig(
                data, cameras, options, progress=not args.no_progress, threads=threads
            )
        except (PoseModelError, RunnerError, ValueError, OSError) as err:
            print(f"eval_track: {err}", file=sys.stderr)
            return 1
    source = (
        str(args.data)
        if args.data
        else f"stg-synth seed {args.seed}, {args.frames} frames, {args.size} px, {args.motion}, "
        f"{RING}-camera ring"
    )
    print(
        f"multi-view tracking chain on {source}: cameras {', '.join(cameras)} (MJPG videos, smoothing "
        f"{'off' if args.no_smoothing else 'on'}, detector {args.detector})"
    )
    print(f"  instants        {report.frames}")
    print(f"  MPJPE           {report.mpjpe_mm:.1f} mm (median {report.median_mpjpe_mm:.1f})")
    print(f"  PA-MPJPE        {report.pa_mpjpe_mm:.1f} mm")
    print(f"  pelvis          {report.pelvis_mm:.1f} mm from the truth (world frame, no alignment)")
    print(f"  accel error     {report.accel_mm:.2f} mm/frame^2")
    print(f"  mask IoU        {report.mask_iou:.3f} (every view)")
    print(f"  confident       {100 * report.confident_fraction:.0f} % of instants (confidence >= 0.5)")
    print(
        f"  tracking speed  {report.fps:.2f} instants/s end to end, {args.rig} views each "
        f"({threads} thread(s), {platform.processor() or platform.machine()})"
    )
    if args.json is not None:
        args.json.write_text(
            json.dumps({"source": source, **report.__dict__, "fps": report.fps}, indent=2) + "\n"
        )
    return 0
