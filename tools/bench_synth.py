#!/usr/bin/env python3
"""Time stg-synth end to end (target: 300 frames at 512x512 in under 2 minutes on the 2-core box).

Runs the generator with the default settings (every camera it renders included: the training
camera on every frame, the held-out ring every 30th frame) into a temporary folder, then, in
the same run, measures a baseline: encoding and writing the same number of images and masks
with OpenCV alone, the floor any generator of this output pays. Prints the stage times, the
ratio to that baseline, and the margin to the 2-minute target.

    python tools/bench_synth.py [--frames 300] [--size 512] [--views 8] [--repeats 1] [--keep DIR]
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

TARGET_SECONDS = 120.0


def _write_floor(folder: Path, count: int) -> float:
    """Seconds to encode + write ``count`` of the generated images and their masks again."""
    import cv2

    from stg_node.data.synth.writer import PNG_COMPRESSION

    images = sorted(folder.glob("Camera_B*/*.png"))[:count]
    arrays = [
        (cv2.imread(str(p)), cv2.imread(str(folder / "mask" / p.relative_to(folder)), 0)) for p in images
    ]
    scratch = folder / "_floor"
    scratch.mkdir()
    start = time.perf_counter()
    for i, (image, mask) in enumerate(arrays):
        cv2.imwrite(str(scratch / f"{i}.png"), image, [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION])
        cv2.imwrite(str(scratch / f"{i}_m.png"), mask, [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION])
    elapsed = time.perf_counter() - start
    shutil.rmtree(scratch)
    return elapsed * count / max(len(images), 1)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--views", type=int, default=8, help="held-out cameras (rendered every 30th frame)")
    parser.add_argument("--motion", default="mixed")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--keep", type=Path, default=None, help="keep the last output in this folder")
    args = parser.parse_args(argv)

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from stg_node.logs import configure_logging
    from stg_node.threads import configure_threads

    configure_logging("WARNING")
    threads = configure_threads()
    import torch

    from stg_node.body import load_body_model
    from stg_node.data.synth.generate import SynthConfig, generate

    body = load_body_model()
    totals, floors, results = [], [], []
    with tempfile.TemporaryDirectory(prefix="bench_synth_") as tmp:
        for repeat in range(args.repeats):
            out = Path(tmp) / f"run{repeat}"
            config = SynthConfig(
                out=out,
                seed=0,
                num_frames=args.frames,
                size=args.size,
                motion=args.motion,
                num_novel_views=args.views,
            )
            result = generate(config, body=body, progress=True)
            totals.append(result.timings["total"])
            floors.append(_write_floor(out, result.num_views))
            results.append(result)
            if args.keep is not None and repeat == args.repeats - 1:
                shutil.rmtree(args.keep, ignore_errors=True)
                shutil.copytree(out, args.keep)
            shutil.rmtree(out)

    result = results[-1]
    total = statistics.median(totals)
    floor = statistics.median(floors)
    timings = result.timings
    print()
    print(
        f"stg-synth benchmark  {datetime.date.today()}  {platform.node()}  {platform.machine()}  "
        f"cpus={os.cpu_count()}  threads={threads}  torch {torch.__version__}"
    )
    print(
        f"workload: {args.frames} frames, {args.size}x{args.size}, motion {args.motion}, "
        f"{result.num_views} views rendered (1 training camera x {args.frames} + {args.views} held-out x "
        f"{len(result.metadata['rendered'].get('Camera_B2', []))}), "
        f"supersample {result.metadata['supersample']}"
    )
    print(f"  body + floor placement   {timings['body']:7.2f} s")
    print(f"  garment dynamics         {timings['garment']:7.2f} s")
    per_view_ms = 1000 * timings["render"] / result.num_views
    print(f"  rasterize + shade        {timings['render']:7.2f} s   ({per_view_ms:.0f} ms/view)")
    print(f"  render + write (overlap) {timings['render_and_write']:7.2f} s")
    print(f"  total (median of {args.repeats})     {total:7.2f} s   ({result.num_views / total:.1f} views/s)")
    print(f"baseline (same run): PNG encode+write of the same {result.num_views} images+masks: {floor:.2f} s")
    print(f"ratio total / baseline: {total / floor:.1f}x")
    print(
        f"target {TARGET_SECONDS:.0f} s: {'MET' if total < TARGET_SECONDS else 'MISSED'} "
        f"({total / TARGET_SECONDS:.2f} of the budget)"
    )
    return 0 if total < TARGET_SECONDS else 1


if __name__ == "__main__":
    sys.exit(main())
