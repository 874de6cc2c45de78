#!/usr/bin/env python3
"""Speed of the live tracker (keypoints + SMPL fit + smoothing + mask) per frame, by stage and input size.

The estimator must keep up with a camera (30 frames/s) on this CPU at 256-512 px. Without a
camera, frames come from a generated stg-synth sequence (a person in motion, so the tracker
tracks rather than re-detects); each size is fed the same frames scaled to that long side. The
same run times the bare landmark network on the same inputs: the floor any BlazePose tracker
pays, and the baseline the ratio is given against.

``--node`` adds the figure a user of the running system sees: the tracker node in its own
process under stg-launch's supervisor (mode live, its built-in estimator), fed camera/frame
messages at ``--fps`` (a camera: the node tracks the newest frame and skips the ones that came
while it worked), for ``--seconds`` after a warm-up; poses per second, the share of camera
frames that got a pose, and the latency from the frame's stamp to the pose's arrival. The
frames play forwards then backwards, so the motion never jumps. Its baseline is the library's
own rate above (1000 / total ms, at most the camera's).

    python tools/bench_track.py [--sizes 256 384 512] [--frames 120] [--repeats 2] [--threads 1]
    python tools/bench_track.py --node [--seconds 20] [--fps 30] [--max-gap 2.0]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

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
    parser.add_argument("--node", action="store_true", help="also time the tracker node at camera rate")
    parser.add_argument("--fps", type=float, default=CAMERA_RATE, help="--node: camera rate (default 30)")
    parser.add_argument("--seconds", type=float, default=20.0, help="--node: measured time per size")
    parser.add_argument("--warmup", type=float, default=3.0, help="--node: seconds before measuring")
    parser.add_argument(
        "--max-gap", type=float, default=None, help="--node: the estimator's max_gap_s (default: its own)"
    )
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
    library_fps: dict[int, float] = {}
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
        library_fps[size] = fps
        print(
            f"{size:>5} {med['detect']:>10.1f} {med['fit']:>8.1f} {med['mask']:>8.1f} {med['total']:>9.1f} "
            f"{fps:>6.1f} {net_ms:>12.1f} {med['total'] / net_ms:>6.2f}"
        )
    verdict = "keeps up with" if worst_fps >= CAMERA_RATE else "falls behind"
    print(
        f"slowest size: {worst_fps:.1f} frames/s: {verdict} a {CAMERA_RATE:.0f} fps camera "
        "(medians per frame)"
    )
    if args.node:
        node_bench(args, source, library_fps)
    return 0


def play_camera(camera, frames: list, K, fps: float, stop, sent: list[int]) -> None:
    """Publish ``frames`` on raw/camera/frame at ``fps``, round and round, until ``stop`` is set;
    append each frame's stamp to ``sent``."""
    from stg_node.bus import Frame

    start = time.monotonic()
    for i in range(10**9):
        if stop.wait(max(0.0, start + i / fps - time.monotonic())):
            return
        image = frames[i % len(frames)]
        frame = Frame(index=i, time=i / fps, image=image, K=K, R=np.eye(3), t=np.zeros(3))
        stamp = time.time_ns()
        camera.publish(frame, "raw/camera/frame", stamp_ns=stamp)
        sent.append(stamp)


def time_node(args, size: int, frames: list) -> tuple[int, list[tuple[float, float]]]:
    """The tracker node fed ``frames`` at camera rate: frames offered in the measured window, and
    (latency ms, confidence) of each pose of a frame stamped in it."""
    import json
    import threading

    from bench_pipeline import start_launch, stop_launch, wait_ready

    from stg_node.bus import Bus, BusConfig, Subscriber
    from stg_node.tracking.camera import from_fov

    options = {"max_side": size, **({} if args.max_gap is None else {"max_gap_s": args.max_gap})}
    params = {"mode": "live", "estimator_params": options, "input_topic": "raw/camera/frame"}
    nodes = f"- name: tracker\n  kind: tracker\n  params: {json.dumps(params)}\n"
    with tempfile.TemporaryDirectory(prefix="bench_track_node_") as tmp:
        launcher, thread, url = start_launch(Path(tmp), "track", nodes)
        try:
            wait_ready(url, {"tracker"})
            with (
                Bus(url, node="camera", heartbeat_s=0) as camera,
                Subscriber(BusConfig(url=url), ["body/pose"], keep_last=False) as poses,
            ):
                camera.publisher.wait_for_subscribers("raw/camera/frame", 30)
                stop, sent = threading.Event(), []
                K = from_fov(size, size).K
                player = threading.Thread(
                    target=play_camera, args=(camera, frames, K, args.fps, stop, sent), daemon=True
                )
                player.start()
                begin = time.time_ns() + int(args.warmup * 1e9)
                end = begin + int(args.seconds * 1e9)
                got = []
                while time.time_ns() < end + int(1e9):  # a last second for the poses on their way
                    msg = poses.recv(timeout=0.2)
                    if msg is not None and begin <= msg.header.stamp_ns < end:
                        got.append(((time.time_ns() - msg.header.stamp_ns) / 1e6, msg.confidence))
                stop.set()
                player.join(5)
        finally:
            stop_launch(launcher, thread)
    return sum(1 for stamp in sent if begin <= stamp < end), got


def node_bench(args, source: list, library_fps: dict[int, float]) -> None:
    """The tracker node in its own process, fed at camera rate; one table row per size."""
    import cv2

    print(
        f"\ntracker node (own process, mode live) fed at {args.fps:g} fps for {args.seconds:g} s after "
        f"{args.warmup:g} s warm-up; max_gap_s {'default' if args.max_gap is None else args.max_gap}"
    )
    print(
        f"{'size':>5} {'frames':>7} {'poses':>6} {'poses/s':>8} {'tracked':>8} {'conf>=.5':>9} "
        f"{'latency ms':>11} {'p90 ms':>7} {'library fps':>12} {'ratio':>6}"
    )
    order = source + source[-2:0:-1]  # forwards, then backwards: no jump when it repeats
    for size in args.sizes:
        frames = [cv2.resize(f, (size, size), interpolation=cv2.INTER_AREA) for f in order]
        offered, got = time_node(args, size, frames)
        rate = len(got) / args.seconds
        latency = sorted(ms for ms, _ in got) or [float("nan")]
        sure = sum(1 for _, c in got if c >= 0.5) / max(1, len(got))
        baseline = min(library_fps[size], args.fps)
        tracked = len(got) / max(1, offered)
        print(
            f"{size:>5} {offered:>7} {len(got):>6} {rate:>8.1f} {tracked:>8.0%} {sure:>9.0%} "
            f"{statistics.median(latency):>11.1f} {latency[int(0.9 * (len(latency) - 1))]:>7.1f} "
            f"{baseline:>12.1f} {rate / baseline:>6.2f}"
        )


if __name__ == "__main__":
    sys.exit(main())
