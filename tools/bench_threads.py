#!/usr/bin/env python3
"""Measure torch CPU speed with 1 vs N intra-op threads, on idle and on busy cores.

Chooses stg_node.threads.DEFAULT_THREADS. The workloads mirror the trainer's hot
spots (a colour MLP over all Gaussians, LBS of 50k points, SSIM's separable
convolutions on a 512x512 image). "busy" runs a competing process that keeps one
core fully loaded, as the other nodes of a launch do.

    python tools/bench_threads.py [--threads 1 2] [--repeats 20]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import platform
import statistics
import subprocess
import sys
import time


def _spin(stop):
    x = 0
    while not stop.is_set():
        for _ in range(10000):
            x += 1


def _workloads():
    import torch
    import torch.nn.functional as F

    torch.manual_seed(0)
    n = 50_000
    mlp = torch.nn.Sequential(
        torch.nn.Linear(32, 64),
        torch.nn.ReLU(),
        torch.nn.Linear(64, 64),
        torch.nn.ReLU(),
        torch.nn.Linear(64, 3),
    )
    feats = torch.randn(n, 32)

    def color_mlp():
        out = mlp(feats).sigmoid().sum()
        out.backward()

    points = torch.randn(n, 3, requires_grad=True)
    weights = torch.softmax(torch.randn(n, 24), dim=1)
    bones = torch.randn(24, 4, 4)

    def lbs():
        transforms = (weights @ bones.view(24, 16)).view(n, 4, 4)
        homo = torch.cat([points, torch.ones(n, 1)], dim=1)
        moved = torch.einsum("nij,nj->ni", transforms, homo)[:, :3]
        moved.square().sum().backward()

    img = torch.rand(1, 3, 512, 512, requires_grad=True)
    ref = torch.rand(1, 3, 512, 512)
    g = torch.exp(-((torch.arange(11) - 5.0) ** 2) / (2 * 1.5**2))
    g = (g / g.sum()).view(1, 1, 1, 11).repeat(3, 1, 1, 1)

    def blur(x):
        x = F.conv2d(x, g, groups=3)
        return F.conv2d(x, g.transpose(2, 3), groups=3)

    def ssim():
        mu_x, mu_y = blur(img), blur(ref)
        sxx = blur(img * img) - mu_x**2
        syy = blur(ref * ref) - mu_y**2
        sxy = blur(img * ref) - mu_x * mu_y
        c1, c2 = 0.01**2, 0.03**2
        s = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2))
        (1 - s.mean()).backward()

    return {"color_mlp_fwd_bwd": color_mlp, "lbs_50k_fwd_bwd": lbs, "ssim_512_fwd_bwd": ssim}


def _measure(threads: int, repeats: int) -> dict:
    import torch

    torch.set_num_threads(threads)
    result = {}
    for name, fn in _workloads().items():
        for _ in range(3):
            fn()
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        result[name] = statistics.median(times)
    return result


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--child", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child is not None:
        print(json.dumps(_measure(args.child, args.repeats)))
        return 0

    rows = {}
    for load in ("idle", "busy"):
        stop = mp.Event()
        spinner = mp.Process(target=_spin, args=(stop,), daemon=True) if load == "busy" else None
        if spinner:
            spinner.start()
            time.sleep(0.5)
        try:
            for t in args.threads:
                out = subprocess.run(
                    [sys.executable, __file__, "--child", str(t), "--repeats", str(args.repeats)],
                    check=True,
                    capture_output=True,
                    text=True,
                ).stdout
                rows[(load, t)] = json.loads(out.strip().splitlines()[-1])
        finally:
            if spinner:
                stop.set()
                spinner.join()

    base = args.threads[0]
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"python {platform.python_version()}"
    )
    print(f"{'load':5} {'threads':>7} {'workload':22} {'median ms':>10} {'vs ' + str(base) + ' thr':>9}")
    for (load, t), res in rows.items():
        for name, sec in res.items():
            ratio = rows[(load, base)][name] / sec
            print(f"{load:5} {t:>7} {name:22} {sec * 1e3:>10.2f} {ratio:>8.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
