"""The focal length from the footage against the truth (issue 26), through stg-track's own pipeline.

    python tools/bench_focal.py capture --out runs/bench_focal [--size 256 --frames 120]
    python tools/bench_focal.py table --out runs/bench_focal

``capture`` renders the ``stg-synth`` subjects (the ``approach`` walk, feet planted, at 30-90
degree fields of view; the ``still`` subject) and runs ``stg-track``'s pipeline (track_to_file,
no --intrinsics, no --fov) on camera 1 of each, keeping the first pass's observations (the
detector's keypoints, exactly what stg-track hands to the estimator) beside the poses file.
``table`` runs the estimator (stg_node.tracking.focal.estimate_focal) on those observations, as
stg-track does at the end of its first pass, and prints the estimate against the truth: the
detection (minutes a subject on a shared box) is done once while the estimator is developed,
and the capture skips the estimator (its run keeps the default field of view).
"""

from __future__ import annotations

import argparse
import json
import math
import pickle
import time
from pathlib import Path

# (motion, true horizontal FOV, camera distance m): the approach walk comes 1.5 m towards the
# camera from the distance and goes 1.5 m beyond it; the distances keep it whole in the picture.
CASES = (
    ("approach", 30, 6.5),
    ("approach", 45, 5.0),
    ("still", 45, 5.0),
    ("approach", 90, 3.0),
    ("approach", 60, 4.0),
    ("approach", 75, 3.5),
)


def capture(args) -> None:
    import stg_node.tracking.focal as focal_module
    from stg_node.data.synth import SynthConfig, generate
    from stg_node.tracking.pipeline import TrackOptions, track_to_file

    real = focal_module.estimate_focal
    for motion, fov, distance in CASES:
        name = f"{motion}_{fov}"
        keep = args.out / f"{name}.observations.pkl"
        if keep.is_file():
            continue
        data = args.out / "data" / name
        if not (data / "synth.json").is_file():
            filmed = dict(motion=motion, fov_deg=float(fov), camera_distance=distance)
            config = SynthConfig(out=data, overwrite=True, num_frames=args.frames, size=args.size,
                                 num_novel_views=0, **filmed)  # fmt: skip
            generate(config, progress=False)
        seen: dict = {}

        def keeping(observations, body, layout, width, height, seen=seen, **kw):  # kept, estimated later
            seen.update(observations=observations, width=width, height=height)
            return focal_module.FocalEstimate(0.0, 65.0, 65.0, 65.0, False, "captured for the bench", 0)

        focal_module.estimate_focal = keeping
        t0 = time.perf_counter()
        try:
            poses = args.out / f"{name}.npz"
            track_to_file(data / "Camera_B1", poses, TrackOptions(fps=30.0), progress=False)
        finally:
            focal_module.estimate_focal = real
        seen.update(motion=motion, fov=fov, distance=distance, seconds=time.perf_counter() - t0)
        keep.write_bytes(pickle.dumps(seen))
        print(f"{name}: tracked in {seen['seconds']:.0f} s", flush=True)


def table(args) -> None:
    from stg_node.tracking.focal import estimate_focal
    from stg_node.tracking.pipeline import TrackOptions, build_tracker

    rows = []
    for motion, fov, distance in CASES:
        keep = args.out / f"{motion}_{fov}.observations.pkl"
        if not keep.is_file() or (args.cases and f"{motion}_{fov}" not in args.cases.split(",")):
            continue
        seen = pickle.loads(keep.read_bytes())
        tracker, body = build_tracker(TrackOptions(fps=30.0), seen["width"], seen["height"], 1)
        t0 = time.perf_counter()
        found = estimate_focal(seen["observations"], body, tracker.layout, seen["width"], seen["height"])
        error = math.tan(math.radians(fov) / 2) / math.tan(math.radians(found.fov_deg) / 2) - 1
        row = dict(motion=motion, true_fov=fov, distance=distance, estimate=round(found.fov_deg, 1),
                   interval=[round(found.low_fov_deg, 1), round(found.high_fov_deg, 1)],
                   focal_error_percent=round(100 * error, 1), sure=found.sure, reason=found.reason,
                   stride=found.stride, seconds=round(time.perf_counter() - t0))  # fmt: skip
        rows.append(row)
        print(json.dumps(row), flush=True)
    name = "table.json" if not args.cases else f"table_{args.cases.replace(',', '_')}.json"
    (args.out / name).write_text(json.dumps(rows, indent=1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("command", choices=("capture", "table"))
    parser.add_argument("--out", type=Path, default=Path("runs/bench_focal"))
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--cases", default="", help="table: only these (e.g. approach_30,still_45)")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    {"capture": capture, "table": table}[args.command](args)


if __name__ == "__main__":
    main()
