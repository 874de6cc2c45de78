"""What shading and well-shaped Gaussians cost: training time and render speed, each configuration
against today's baked colour, measured step by step in alternation in one process.

    python tools/bench_shading.py [--data DIR] [--iterations N] [--configs NAME ...] [--renders 20]

Every configuration is the fast preset with some of issue 21's parts switched on or off
(``CONFIGS``); ``baked`` is the colour as it was before them (no shading, spherical initial
Gaussians, no scale cap, no isometry term). The trainers are built side by side and stepped in
turn (one step of each, then the next), so the load of a shared machine falls on all alike; each
one's training time is the sum of its own steps (optical flow and frames are loaded once, before).
Then each trained model renders the same held-out views in turn (pose + colour + shading +
splat), and the medians give the FPS. Reported: training seconds and the ratio to ``baked``, FPS
and the ratio, Gaussians, and the 99th percentile of the posed scale ratio (largest / smallest
axis). The data is generated if not given: the room-light subject with a held-out turn
(tools/tradeoff.py's ``room_turn_held_out``), 125 frames at 512 x 512.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tools"))

from tradeoff import BAKED  # noqa: E402  (the colour before shading)

CONFIGS = {
    "baked": BAKED,  # today's colour: the light baked in, spheres, no cap, no isometry
    "shaded": {},  # the fast preset as it is now: every part on (the occlusion term included)
    "no_occlusion": {"model.occlusion": False},  # shaded without what the body casts on itself
    "no_shading": {"model.shading": False},
    "no_scale_cap": {"model.max_scale_ratio": 0.0},
    "no_isometry": {"loss.isometry": 0.0},
    "sphere_init": {"model.init_flatness": 1.0},
    "no_joint_shrink": {"model.joint_shrink": False},
    "occlusion": {"model.occlusion": True},  # what the body casts on itself (occlusion.py; the default)
    "outward_normals": {"model.normal_sign": "outward"},  # outward normals in training (shading.py)
}


def ensure_data(path: str | None, size: int) -> Path:
    if path:
        return Path(path)
    import tradeoff

    scale = tradeoff.Scale("bench", size, 125, 2, 10, 2, 1.0, 1.0, 1, 1)
    cache = Path(tempfile.gettempdir()) / "stg_bench_shading"
    return tradeoff.ensure_subject(cache, "room_turn_held_out", scale)


def main(argv=None) -> int:
    from stg_node.threads import configure_threads

    p = argparse.ArgumentParser(prog="bench_shading.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--data", default=None, help="an stg-synth folder (default: generated once in /tmp)")
    p.add_argument("--size", type=int, default=512, help="image size of the generated data and training")
    p.add_argument("--iterations", type=int, default=None, help="training steps (default: the fast preset's)")
    p.add_argument("--configs", nargs="+", default=["baked", "shaded"], choices=list(CONFIGS))
    p.add_argument("--renders", type=int, default=20, help="timed renders per model")
    p.add_argument("--threads", default="1")
    p.add_argument("--json", default=None, help="also write the results to this JSON file")
    args = p.parse_args(argv)
    configure_threads(args.threads)

    from stg_node.avatar import Trainer, preset
    from stg_node.avatar.data_spec import DataSpec
    from stg_node.avatar.loading import corrected
    from stg_node.avatar.model import BodyState, Camera3, render
    from stg_node.data.flow import FlowCache

    data = ensure_data(args.data, args.size)
    spec = DataSpec(str(data.resolve()), "synthetic", size=args.size)
    frames = list(spec.open("train"))
    configs = {name: preset("fast").replace(**CONFIGS[name]) for name in args.configs}
    if args.iterations:
        configs = {n: c.replace(iterations=args.iterations) for n, c in configs.items()}
    trainers = {}
    for name, config in configs.items():
        trainer = Trainer(config, seed=0, flow_cache=FlowCache(data / "flow_cache"))
        trainer.add_frames(frames)
        trainers[name] = trainer
    iterations = next(iter(configs.values())).iterations
    for _ in range(iterations):
        for trainer in trainers.values():
            trainer.step()
    held_out = list(spec.open("novel_pose"))[: max(1, min(4, args.renders))]
    times: dict[str, list[float]] = {name: [] for name in trainers}
    for i in range(args.renders + 1):
        sample = held_out[i % len(held_out)]
        cam = Camera3.from_camera(sample.camera)
        for name, trainer in trainers.items():
            model = trainer.model.eval()
            t0 = time.perf_counter()
            with torch.no_grad():
                u = model.pose_index.time_for(sample.smpl.poses)[0]
                posed = model.pose(
                    BodyState.from_smpl(corrected(sample.smpl, None)), u, cam.center, skip_inactive=True
                )
                render(posed, cam, background=0.0)
            if i:  # the first render of each warms caches
                times[name].append(time.perf_counter() - t0)
    base = "baked" if "baked" in trainers else next(iter(trainers))
    results = {}
    for name, trainer in trainers.items():
        stats = trainer.stats()
        results[name] = {
            "train_seconds": trainer.train_seconds,
            "render_ms": 1e3 * statistics.median(times[name]),
            "gaussians": stats["gaussians"],
            "scale_ratio_p99": stats["scale_ratio_p99"],
            "changes": CONFIGS[name],
        }
    print(f"`python tools/bench_shading.py {' '.join(argv if argv is not None else sys.argv[1:])}`")
    print(f"machine: {platform.machine()}, {torch.get_num_threads()} torch thread(s); data {data}")
    print(f"{iterations} training steps per configuration, alternating; {args.renders} renders each\n")
    print("| configuration | train time | x baked | render ms | FPS | x baked FPS | Gaussians | p99 ratio |")
    print("|---|---|---|---|---|---|---|---|")
    b = results[base]
    for name, r in results.items():
        print(
            f"| {name} | {r['train_seconds']:.0f} s | {r['train_seconds'] / b['train_seconds']:.2f} "
            f"| {r['render_ms']:.1f} | {1e3 / r['render_ms']:.1f} | {b['render_ms'] / r['render_ms']:.2f} "
            f"| {r['gaussians']:,} | {r['scale_ratio_p99']:.1f} |"
        )
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
