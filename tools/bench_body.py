#!/usr/bin/env python
"""Benchmark the body's hot paths on CPU: skinning 50k points / rotations, canonical transforms,
and a forward of the open body, each against a plain baseline measured in the same run.

Baselines: skinning by a loop over the 24 joints (the obvious implementation); inverse skinning
with torch.linalg.inv of every blended matrix; polar factors by torch.linalg.svd.

    python tools/bench_body.py [--points 50000] [--repeats 20]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stg_node.body import (  # noqa: E402
    blend_transforms,
    canonical_transforms,
    load_body_model,
    skin_points,
    skin_rotations,
)
from stg_node.body.lbs import matrix_to_quaternion, quaternion_to_matrix  # noqa: E402
from stg_node.data.synth.motions import make_motion  # noqa: E402
from stg_node.logs import configure_logging  # noqa: E402
from stg_node.threads import configure_threads  # noqa: E402


def timed(fn, repeats: int) -> float:
    fn()  # warm-up
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        runs.append(time.perf_counter() - start)
    return statistics.median(runs) * 1000.0


def loop_skin(points, weights, transforms):
    out = torch.zeros(transforms.shape[0], points.shape[0], 3)
    for j in range(transforms.shape[1]):
        moved = points @ transforms[:, j, :3, :3].transpose(-1, -2) + transforms[:, j, None, :3, 3]
        out += weights[:, j, None] * moved
    return out


def inv_skin(points, weights, transforms):
    blended = blend_transforms(weights, transforms)
    inv = torch.linalg.inv(blended[..., :3, :3])
    return (inv @ (points - blended[..., :3, 3])[..., None]).squeeze(-1)


def svd_rotations(quats, weights, transforms):
    linear = blend_transforms(weights, transforms)[..., :3, :3]
    u, _, vh = torch.linalg.svd(linear)
    return matrix_to_quaternion(u @ vh @ quaternion_to_matrix(quats))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", type=int, default=50_000)
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args(argv)
    configure_logging()
    threads = configure_threads()
    torch.manual_seed(0)
    body = load_body_model(None)
    motion = make_motion("walk", 2, 30.0, np.random.default_rng(0))
    transforms = canonical_transforms(
        body,
        torch.as_tensor(motion.betas),
        torch.as_tensor(motion.poses[:1]),
        torch.as_tensor(motion.Rh[:1]),
        torch.as_tensor(motion.Th[:1]),
    )
    idx = torch.randint(0, body.num_vertices, (args.points,))
    points = body.v_template[idx] + 0.01 * torch.randn(args.points, 3)
    weights = body.weights[idx]
    quats = torch.nn.functional.normalize(torch.randn(args.points, 4), dim=-1)
    posed = skin_points(points, weights, transforms)
    assert torch.allclose(posed, loop_skin(points, weights, transforms), atol=1e-5)
    rows = [
        (
            f"skin_points, {args.points} points",
            timed(lambda: skin_points(points, weights, transforms), args.repeats),
            "loop over 24 joints",
            timed(lambda: loop_skin(points, weights, transforms), args.repeats),
        ),
        (
            f"skin_points inverse, {args.points} points",
            timed(lambda: skin_points(posed, weights, transforms, inverse=True), args.repeats),
            "torch.linalg.inv",
            timed(lambda: inv_skin(posed, weights, transforms), args.repeats),
        ),
        (
            f"skin_rotations (quaternions), {args.points}",
            timed(lambda: skin_rotations(quats, weights, transforms), args.repeats),
            "polar factor by torch.linalg.svd",
            timed(lambda: svd_rotations(quats, weights, transforms), args.repeats),
        ),
    ]
    poses = torch.as_tensor(motion.poses[:1])
    fwd = timed(lambda: body(poses=poses), args.repeats)
    canon = timed(lambda: canonical_transforms(body, None, poses), args.repeats)
    print(f"threads: {threads}; torch {torch.__version__}; open body {body.num_vertices} vertices")
    print("| operation | ours | baseline | baseline time | speed-up |")
    print("|---|---|---|---|---|")
    for name, ours, base_name, base in rows:
        print(f"| {name} | {ours:.1f} ms | {base_name} | {base:.1f} ms | {base / ours:.2f}x |")
    print(f"| open body forward (1 pose) | {fwd:.1f} ms | - | - | - |")
    print(f"| canonical_transforms (1 pose) | {canon:.1f} ms | - | - | - |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
