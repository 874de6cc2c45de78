#!/usr/bin/env python3
"""Speed of the live tracker (keypoints + SMPL fit + smoothing + mask) per frame, by stage and input size.

The estimator must keep up with a camera (30 frames/s) on this CPU at 256-512 px. Without a
camera, frames come from a generated stg-synth sequence (a person in motion, so the tracker
tracks rather than re-detects); each size is fed the same frames scaled to that long side. The
same run times the bare landmark network on the same inputs: the floor any BlazePose tracker
pays, and the baseline the ratio is given against.

    python tools/bench_track.py [--sizes 256 384 512] [--frames 120] [--repeats 2] [--threads 1]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's stg_node first

CAMERA_RATE = 30.0


def main(argv: list[str] | None = None) -> int:
    from stg_node.logs import configure_logging
    from stg_node.threads import configure_threads

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 384, 512], help="long sides to test")
    parser.add_argument("--frames", type=int, default=120, help="frames per size (default %(default)s)")
    parser.add_argument("--repeats", type=int, default=2, help="passes over the frames (default %(default)s)")
    parser.add_argument("--mask-method", default="segmentation", help="mask method (default %(default)s)")
    parser.add_argument("--threads", default=None, help="CPU threads (default: STG_THREADS or 1)")
    args = parser.parse_args(argv)
    if args.frames < 10 or args.repeats < 1 or any(s < 64 for s in args.sizes):
        parser.error("--frames >= 10, --repeats >= 1 and --sizes >= 64 please")
    configure_logging("WARNING")
    threads = configure_threads(args.threads)

    import cv2

    from stg_node.body import load_body_model
    from stg_node.data.io import read_image
    from stg_node.data.synth import SynthConfig, generate
    from stg_node.tracking.blazepose import landmark_input
    from stg_node.tracking.camera import from_fov
    from stg_node.tracking.detectors import make_detector
    from stg_node.tracking.masks import make_masker
    from stg_node.tracking.model_files import PoseModelError
    from stg_node.tracking.roi import Roi
    from stg_node.tracking.tracker import Tracker, TrackerConfig

    body = load_body_model()
    with tempfile.TemporaryDirectory(prefix="bench_track_") as tmp:
        folder = Path(tmp) / "synth"
        generate(
            SynthConfig(
                out=folder, num_frames=args.frames, size=max(args.sizes), num_novel_views=0, motion="mixed"
            ),
            body=body,
            progress=False,
        )
        source = [read_image(p) for p in sorted((folder / "Camera_B1").glob("*.png"))]

    print(
        f"tracker speed, {threads} thread(s), {platform.processor() or platform.machine()}, "
        f"{args.frames} frames x {args.repeats} passes per size, mask {args.mask_method}"
    )
    print(
        f"{'size':>5} {'detect ms':>10} {'fit ms':>8} {'mask ms':>8} {'total ms':>9} {'fps':>6} "
        f"{'net-only ms':>12} {'ratio':>6}"
    )
    worst_fps = float("inf")
    for size in args.sizes:
        frames = [cv2.resize(f, (size, size), interpolation=cv2.INTER_AREA) for f in source]
        try:
            detector = make_detector("blazepose", threads=threads)
        except PoseModelError as err:
            print(f"bench_track: {err}", file=sys.stderr)
            return 1
        tracker = Tracker(
            detector, body, from_fov(size, size), TrackerConfig(max_side=0), make_masker(args.mask_method)
        )
        stages = {"detect": [], "fit": [], "mask": [], "total": []}
        for repeat in range(args.repeats):
            tracker.reset()
            for i, frame in enumerate(frames):
                tracker.estimate(frame, (repeat * len(frames) + i) / CAMERA_RATE)
                if i >= 5:  # the first frames run the person detector and the shape calibration
                    for key in stages:
                        stages[key].append(getattr(tracker.times, key))
        # Baseline: the landmark network alone on the same crops (no detector, fit or mask).
        roi = Roi(size / 2, size / 2, size * 0.9, 0.0)
        net = detector._landmarker
        inputs = [landmark_input(f, roi) for f in frames[:30]]
        net(inputs[0])
        start = time.perf_counter()
        for x in inputs * args.repeats:
            net(x)
        net_ms = (time.perf_counter() - start) / (len(inputs) * args.repeats) * 1000
        med = {k: statistics.median(v) * 1000 for k, v in stages.items()}
        fps = 1000.0 / med["total"]
        worst_fps = min(worst_fps, fps)
        print(
            f"{size:>5} {med['detect']:>10.1f} {med['fit']:>8.1f} {med['mask']:>8.1f} {med['total']:>9.1f} "
            f"{fps:>6.1f} {net_ms:>12.1f} {med['total'] / net_ms:>6.2f}"
        )
    verdict = "keeps up with" if worst_fps >= CAMERA_RATE else "falls behind"
    print(
        f"slowest size: {worst_fps:.1f} frames/s: {verdict} a {CAMERA_RATE:.0f} fps camera "
        "(medians per frame)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
