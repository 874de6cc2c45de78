#!/usr/bin/env python3
"""What an online trainer keeps as a stream goes on: knots, snapshot bytes, Adam bytes, memory, step time.

The pipeline's memory run (bench_pipeline.py ``--only memory``) replays a dataset in a loop, and
every pass restarts the frames' times (the tracker matches frames to the dataset by index and
time), so the trainer never sees more stream time than the dataset lasts: it cannot see what
grows with stream time. Here the avatar Trainer (the class the trainer node drives, configured
as TrainerAdapter.create does: the ``--preset`` with ``max_frames``; ``--nonrigid on`` by
default, so the trial cannot switch the shared bases off on a subject where they do not pay) is
fed the dataset's training frames over and over with times and indices that keep going, as a
live camera's do: one frame every ``--gap-s`` seconds of stream time (a trainer node takes the
newest frame when it has time, so the frames it stores are seconds apart on a sped-up stream)
and ``--steps`` training steps after each. Every ``--every-min`` minutes of stream it records
the shared motion bases' knots, the bytes of the published snapshot and of the dense modules'
Adam moments, the process's resident memory and the median step time; the growth is fitted over
the second half.

With ``--baseline REV`` the same run is made on that git revision (tools/baseline.py exports it),
alternating with today's tree, each in a child process of its own.

    python tools/bench_stream_window.py --data runs/subject --minutes 60 --baseline main --json out.json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def child(args) -> dict:
    if args.root:
        sys.path.insert(0, args.root)
    import dataclasses

    import numpy as np
    import torch

    import stg_node
    from stg_node import avatar
    from stg_node.avatar.data_spec import DataSpec
    from stg_node.avatar.frames import TrainFrame
    from stg_node.avatar.snapshot import model_nbytes
    from stg_node.progress import progress as progress_bar

    torch.set_num_threads(1)
    frames = [
        TrainFrame.from_sample(s) for s in DataSpec(args.data, args.format, size=args.size).open("train")
    ]
    config = dataclasses.replace(
        avatar.preset(args.preset), max_frames=args.max_frames, nonrigid=args.nonrigid
    )
    trainer = avatar.Trainer(config, seed=0)
    total = int(args.minutes * 60 / args.gap_s)
    per_sample = max(int(args.every_min * 60 / args.gap_s), 1)
    rows, step_ms = [], []
    progress = progress_bar(
        total=total, desc=f"stream ({Path(stg_node.__file__).parents[1].name})", unit="frame"
    )
    for i in range(total):
        src = frames[i % len(frames)]
        # indices that skip: a trainer taking the newest frame never stores two consecutive ones
        trainer.add_frame(dataclasses.replace(src, index=2 * i, time=i * args.gap_s))
        for _ in range(args.steps):
            t0 = time.perf_counter()
            trainer.step()
            step_ms.append(1e3 * (time.perf_counter() - t0))
        progress.update(1)
        if (i + 1) % per_sample == 0:
            bases = trainer.model.motion_bases
            dense = trainer.optimizer.dense_state() if trainer.optimizer is not None else {}
            adam = sum(
                v.numel() * v.element_size() for s in dense.values() for v in s.values() if torch.is_tensor(v)
            )
            rows.append(
                {
                    "stream_min": (i + 1) * args.gap_s / 60,
                    "knots": 0 if bases is None else bases.knots,
                    "snapshot_mb": model_nbytes(trainer.model) / 1e6,
                    "dense_adam_mb": adam / 1e6,
                    "pose_index": len(trainer.model.pose_index),
                    "gaussians": trainer.model.table.num,
                    "rss_mb": rss_mb(),
                    "step_ms": float(np.median(step_ms)) if step_ms else float("nan"),
                }
            )
            step_ms = []
    progress.close()
    return {"tree": str(Path(stg_node.__file__).parents[1]), "rows": rows}


def slopes(rows: list[dict]) -> dict:
    """Growth per stream hour over the second half, for every figure."""
    import numpy as np

    half = [r for r in rows if r["stream_min"] >= rows[-1]["stream_min"] / 2]
    t = np.array([r["stream_min"] for r in half]) / 60
    out = {}
    for key in ("knots", "snapshot_mb", "dense_adam_mb", "rss_mb", "step_ms", "pose_index"):
        y = np.array([r[key] for r in half], float)
        out[f"{key}_per_h"] = float(np.polyfit(t, y, 1)[0]) if len(half) >= 2 else float("nan")
        out[f"{key}_end"] = float(y[-1])
    return out


def run_child(args, root: str | None) -> dict:
    cmd = [sys.executable, __file__, "--child", "--data", str(Path(args.data).resolve())]
    for name in (
        "format",
        "size",
        "preset",
        "max_frames",
        "nonrigid",
        "minutes",
        "gap_s",
        "steps",
        "every_min",
    ):
        cmd += [f"--{name.replace('_', '-')}", str(getattr(args, name))]
    if root:
        cmd += ["--root", root]
    out = subprocess.run(cmd, check=True, stdout=subprocess.PIPE, text=True, cwd=root or ROOT)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", required=True, help="a dataset folder (e.g. stg-synth output)")
    parser.add_argument("--format", default="synthetic", help="its format (stg-train's --format)")
    parser.add_argument("--size", type=int, default=128, help="image size (longer side)")
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--max-frames", type=int, default=64, help="the trainer node's default bound")
    parser.add_argument(
        "--nonrigid", default="on", help="the trainer's nonrigid setting (on: the shared bases stay all run)"
    )
    parser.add_argument("--minutes", type=float, default=60.0, help="minutes of stream time")
    parser.add_argument("--gap-s", type=float, default=1.0, help="stream seconds between stored frames")
    parser.add_argument("--steps", type=int, default=1, help="training steps after each frame")
    parser.add_argument("--every-min", type=float, default=2.0, help="sample every this many stream minutes")
    parser.add_argument("--baseline", help="also run this git revision (tools/baseline.py), alternating")
    parser.add_argument("--rounds", type=int, default=1, help="runs per tree")
    parser.add_argument("--json", type=Path, help="also write the results here")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--root", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(args)))
        return 0
    trees = {"today": None}
    if args.baseline:
        sys.path.insert(0, str(ROOT / "tools"))
        from baseline import export_revision

        trees = {f"baseline {args.baseline}": str(export_revision(args.baseline)), "today": None}
    results: dict[str, list] = {name: [] for name in trees}
    for _ in range(args.rounds):
        for name, root in trees.items():
            results[name].append(run_child(args, root))
    report = {
        name: {"runs": runs, "growth": [slopes(r["rows"]) for r in runs]} for name, runs in results.items()
    }
    for name, entry in report.items():
        for growth in entry["growth"]:
            print(
                f"{name:>20}: knots {growth['knots_end']:.0f} ({growth['knots_per_h']:+.0f}/h), "
                f"snapshot {growth['snapshot_mb_end']:.2f} MB ({growth['snapshot_mb_per_h']:+.2f} MB/h), "
                f"dense Adam {growth['dense_adam_mb_end']:.2f} MB "
                f"({growth['dense_adam_mb_per_h']:+.2f} MB/h), "
                f"RSS {growth['rss_mb_end']:.0f} MB ({growth['rss_mb_per_h']:+.1f} MB/h), "
                f"step {growth['step_ms_end']:.0f} ms ({growth['step_ms_per_h']:+.1f} ms/h), "
                f"pose index {growth['pose_index_end']:.0f}"
            )
    if args.json:
        args.json.write_text(
            json.dumps({"args": {k: v for k, v in vars(args).items() if k != "json"}} | report, indent=1)
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
