#!/usr/bin/env python3
"""Rendering speed of stg_node.splat: the cpu backend against the torch reference, same run.

The scene is stg_node.splat.scenes.person_sized_scene: N Gaussians on the surfaces of a
1.8 m standing figure (head, torso, limbs), 3 mm - 3 cm, opacities 0.3 - 1, seen from 3 m by
a camera framing it to 85 % of the image height (an avatar in a telepresence view). For each
thread count a child process is started with STG_THREADS set (stg_node.threads applies it)
and measures, per case: forward (no grad) and forward+backward (grads for all parameters,
a weighted-sum loss) wall time, per-stage timings of the C++ kernels, and the torch
reference on the same scene for the same-run ratio. On a CUDA machine each row adds the cuda
backend (gsplat) forward and forward+backward on the same scene in the same run (run
``stg-splat-prebuild`` first, or the warm-up includes gsplat's first-use build). The load
average is printed with every row: on a shared machine the figures are only comparable
within one run.

    python tools/bench_render.py [--threads 1 2] [--repeats 20] [--torch-repeats 2]
                                 [--cases 10000x256 50000x512] [--no-torch] [--png docs/splat_person.png]
                                 [--baseline REV [--rounds 3]]

With ``--baseline REV`` every child runs once more on that git revision (tools/baseline.py exports
it; its kernels build once), the two trees alternating ``--rounds`` times; a second table gives
the cpu backend's speed-up over the baseline (medians over rounds) and the live-rate targets
(issue 24: forward >= 160 FPS at 10k/256x256 and >= 60 FPS at 50k/512x512 with 2 threads).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if "--root" in sys.argv:  # a child timing another tree (--baseline): import that one's stg_node
    ROOT = Path(sys.argv[sys.argv.index("--root") + 1]).resolve()
sys.path.insert(0, str(ROOT))

TARGETS = {  # the targets for the cpu backend on the 2-core reference machine
    (10_000, 256): {"fwd_fps": 30.0, "fwdbwd_s": 0.12},
    (50_000, 512): {"fwd_fps": 8.0},
}
LIVE_TARGETS = {(10_000, 256, "2"): 160.0, (50_000, 512, "2"): 60.0}  # issue 24: forward FPS, 2 threads


def _time(fn, repeats: int, warmup: int = 2, sync=None) -> dict:
    for _ in range(warmup):
        fn()
    wall, cpu = [], []
    for _ in range(repeats):
        if sync:
            sync()
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        if sync:
            sync()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return {"median_s": statistics.median(wall), "min_s": min(wall), "cpu_s": statistics.median(cpu)}


def _child(args) -> None:
    import torch

    from stg_node.logs import configure_logging
    from stg_node.progress import progress
    from stg_node.splat import rasterize
    from stg_node.splat.scenes import front_camera, person_sized_scene
    from stg_node.threads import configure_threads

    configure_logging("WARNING")
    threads = configure_threads()
    results = []
    for case in progress(args.cases, desc=f"STG_THREADS={threads}", unit="case"):
        n, size = (int(x) for x in case.split("x"))
        scene = person_sized_scene(n, seed=0)
        viewmat, K = front_camera(size, size)
        weights = torch.rand(size, size, 3, generator=torch.Generator().manual_seed(0))
        params = [t.clone().requires_grad_(True) for t in scene.params()]

        def forward(backend, scene=scene, viewmat=viewmat, K=K, size=size):
            with torch.no_grad():
                return rasterize(*scene.params(), viewmat, K, size, size, backend=backend)

        def forward_backward(backend, params=params, viewmat=viewmat, K=K, size=size, weights=weights):
            for p in params:
                p.grad = None
            image, alpha, info = rasterize(*params, viewmat, K, size, size, backend=backend)
            ((image * weights).sum() + alpha.sum()).backward()
            return info

        row = {"n": n, "size": size, "threads": threads, "load_before": os.getloadavg()[0]}
        row["cpu_fwd"] = _time(lambda: forward("cpu"), args.repeats)
        stages = {"project": [], "sort": [], "bin": [], "raster": []}
        for _ in range(5):
            info = forward("cpu")[2]
            stages["project"].append(info["stats"]["project"]["ms"])
            for key in ("sort", "bin", "raster"):
                stages[key].append(info["stats"]["forward"][f"ms_{key}"])
        row["cpu_stages_ms"] = {k: statistics.median(v) for k, v in stages.items()}
        row["n_intersections"] = info["n_intersections"]
        row["cpu_fwdbwd"] = _time(lambda: forward_backward("cpu"), max(5, args.repeats // 2))
        bstages = {"raster_bwd": [], "reduce": [], "project_bwd": []}
        for _ in range(3):
            stats = forward_backward("cpu")["stats"]  # the backward stages arrive with backward()
            bstages["raster_bwd"].append(stats["backward"]["ms_raster"])
            bstages["reduce"].append(stats["backward"]["ms_reduce"])
            bstages["project_bwd"].append(stats["project_backward"]["ms"])
        row["cpu_stages_ms"].update({k: statistics.median(v) for k, v in bstages.items()})
        if not args.no_torch:
            row["torch_fwd"] = _time(lambda: forward("torch"), args.torch_repeats, warmup=1)
            row["torch_fwdbwd"] = _time(lambda: forward_backward("torch"), args.torch_repeats, warmup=1)
        if torch.cuda.is_available():
            try:
                cuda_scene = [t.cuda() for t in scene.params()]
                vm, kk = viewmat.cuda(), K.cuda()

                def cuda_forward(cuda_scene=cuda_scene, vm=vm, kk=kk, size=size):
                    with torch.no_grad():
                        rasterize(*cuda_scene, vm, kk, size, size, backend="cuda")

                cuda_params = [t.clone().requires_grad_(True) for t in cuda_scene]
                cuda_weights = weights.cuda()

                def cuda_forward_backward(cuda_params=cuda_params, vm=vm, kk=kk, size=size, w=cuda_weights):
                    for p in cuda_params:
                        p.grad = None
                    image, alpha, _ = rasterize(*cuda_params, vm, kk, size, size, backend="cuda")
                    ((image * w).sum() + alpha.sum()).backward()

                row["cuda_fwd"] = _time(cuda_forward, args.repeats * 5, warmup=5, sync=torch.cuda.synchronize)
                row["cuda_fwdbwd"] = _time(
                    cuda_forward_backward, args.repeats * 5, warmup=5, sync=torch.cuda.synchronize
                )
                row["cuda_device"] = torch.cuda.get_device_name()
            except Exception as exc:  # report, do not hide: the cuda path is optional here
                row["cuda_error"] = f"{type(exc).__name__}: {exc}"
        row["load_after"] = os.getloadavg()[0]
        results.append(row)
        print(json.dumps(row), flush=True)


def _write_png(path: Path) -> None:
    import cv2
    import torch

    from stg_node.splat import rasterize
    from stg_node.splat.scenes import front_camera, person_sized_scene

    scene = person_sized_scene(50_000, seed=0)
    size = 256
    viewmat, K = front_camera(size, size)
    image, _, info = rasterize(
        *scene.params(), viewmat, K, size, size, background=torch.ones(3), render_depth=True
    )
    depth = info["depth"][..., 0]
    covered = depth > 0
    d = torch.zeros_like(depth)
    d[covered] = 1 - (depth[covered] - depth[covered].min()) / (depth[covered].max() - depth[covered].min())
    depth_rgb = (d[..., None] * torch.tensor([1.0, 0.8, 0.3])).clamp(0, 1)
    panel = torch.cat([image.clamp(0, 1), depth_rgb], dim=1)
    rgb = (panel.numpy() * 255).round().astype("uint8")
    cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(f"wrote {path} ({path.stat().st_size // 1024} KiB)")


def _fmt_ms(s: float) -> str:
    return f"{s * 1e3:.1f} ms"


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--threads", nargs="+", default=["1", "2"], help="STG_THREADS values to measure")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--torch-repeats", type=int, default=2)
    parser.add_argument(
        "--cases", nargs="+", default=["10000x256", "50000x512"], help="NxSIZE (square images)"
    )
    parser.add_argument("--no-torch", action="store_true", help="skip the (slow) torch reference baseline")
    parser.add_argument("--png", type=Path, help="also render the scene (colour | depth) into this PNG")
    parser.add_argument("--baseline", help="also time this git revision, alternating (tools/baseline.py)")
    parser.add_argument("--rounds", type=int, default=1, help="with --baseline: children per tree")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--root", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        _child(args)
        return 0
    if args.png:
        _write_png(args.png)

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from baseline import child_env, export_revision

    trees = {"this tree": ROOT}
    if args.baseline:
        trees["baseline"] = export_revision(args.baseline)
    runs: dict[str, list[list[dict]]] = {name: [] for name in trees}
    names = list(trees)
    for r in range(args.rounds if args.baseline else 1):
        for name in names if r % 2 == 0 else names[::-1]:
            found = []
            for threads in args.threads:
                env = child_env(trees[name], STG_THREADS=str(threads))
                cmd = [
                    sys.executable,
                    __file__,
                    "--child",
                    "--root",
                    str(trees[name]),
                    "--repeats",
                    str(args.repeats),
                    "--torch-repeats",
                    str(args.torch_repeats),
                    "--cases",
                    *args.cases,
                ] + (["--no-torch"] if args.no_torch or name != "this tree" else [])
                # stdout carries the JSON rows; stderr (progress) goes straight to the terminal.
                out = subprocess.run(cmd, env=env, check=True, stdout=subprocess.PIPE, text=True).stdout
                found += [json.loads(line) for line in out.splitlines() if line.startswith("{")]
            runs[name].append(found)
    rows = _median_rows(runs["this tree"])

    print(
        f"date: {datetime.date.today()}  machine: {platform.machine()} {os.cpu_count()} cores, "
        f"python {platform.python_version()}"
    )
    print(
        "| scene | threads | cpu fwd | cpu fwd FPS | cpu fwd+bwd | torch fwd | torch fwd+bwd | "
        "fwd ratio | fwd+bwd ratio | load (1 min) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        fwd, fb = r["cpu_fwd"]["median_s"], r["cpu_fwdbwd"]["median_s"]
        tf = r.get("torch_fwd", {}).get("median_s")
        tfb = r.get("torch_fwdbwd", {}).get("median_s")
        torch_cols = f"{_fmt_ms(tf) if tf else '-'} | {_fmt_ms(tfb) if tfb else '-'}"
        ratios = f"{f'{tf / fwd:.0f}x' if tf else '-'} | {f'{tfb / fb:.0f}x' if tfb else '-'}"
        print(
            f"| {r['n'] // 1000}k Gaussians {r['size']}x{r['size']} | {r['threads']} | {_fmt_ms(fwd)} | "
            f"{1 / fwd:.1f} | {_fmt_ms(fb)} | {torch_cols} | {ratios} | "
            f"{r['load_before']:.1f}-{r['load_after']:.1f} |"
        )
    print()
    print(
        "| scene | threads | project | sort | bin | raster | raster bwd | reduce | project bwd | "
        "intersections | cpu time fwd / fwd+bwd |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        st = r["cpu_stages_ms"]
        print(
            f"| {r['n'] // 1000}k {r['size']}x{r['size']} | {r['threads']} | {st['project']:.1f} | "
            f"{st['sort']:.1f} | {st['bin']:.1f} | {st['raster']:.1f} | {st['raster_bwd']:.1f} | "
            f"{st['reduce']:.1f} | {st['project_bwd']:.1f} | {r['n_intersections']} | "
            f"{_fmt_ms(r['cpu_fwd']['cpu_s'])} / {_fmt_ms(r['cpu_fwdbwd']['cpu_s'])} |"
        )
    for r in rows:
        if "cuda_fwd" in r:
            print(
                f"cuda ({r['cuda_device']}) {r['n']} Gaussians {r['size']}^2: "
                f"{1 / r['cuda_fwd']['median_s']:.0f} FPS forward, "
                f"{_fmt_ms(r['cuda_fwdbwd']['median_s'])} forward+backward; same run, cpu backend "
                f"{r['threads']} thread(s): {r['cpu_fwd']['median_s'] / r['cuda_fwd']['median_s']:.0f}x / "
                f"{r['cpu_fwdbwd']['median_s'] / r['cuda_fwdbwd']['median_s']:.0f}x slower"
            )
        elif "cuda_error" in r:
            print(f"cuda failed: {r['cuda_error']}")
    print()
    failed = False
    if args.baseline:
        failed |= _print_against_baseline(rows, _median_rows(runs["baseline"]), args.baseline)
    for r in rows:
        target = TARGETS.get((r["n"], r["size"]), {})
        fps = 1 / r["cpu_fwd"]["median_s"]
        if "fwd_fps" in target:
            ok = fps >= target["fwd_fps"]
            failed |= not ok
            print(
                f"target {r['n']}@{r['size']} threads={r['threads']}: forward {fps:.1f} FPS "
                f">= {target['fwd_fps']} {'OK' if ok else 'MISSED'}"
            )
        if "fwdbwd_s" in target:
            ok = r["cpu_fwdbwd"]["median_s"] <= target["fwdbwd_s"]
            failed |= not ok
            print(
                f"target {r['n']}@{r['size']} threads={r['threads']}: fwd+bwd "
                f"{r['cpu_fwdbwd']['median_s']:.3f} s <= {target['fwdbwd_s']} {'OK' if ok else 'MISSED'}"
            )
    return 1 if failed else 0


def _median_rows(rounds: list[list[dict]]) -> list[dict]:
    """Rows of several rounds merged: medians of the timings, the load's range."""
    merged = []
    for i, first in enumerate(rounds[0]):
        same = [rows[i] for rows in rounds]
        row = dict(first)
        for key in ("cpu_fwd", "cpu_fwdbwd", "torch_fwd", "torch_fwdbwd"):
            if key in first:
                row[key] = {k: statistics.median(r[key][k] for r in same) for k in first[key]}
        row["cpu_stages_ms"] = {
            k: statistics.median(r["cpu_stages_ms"][k] for r in same) for k in first["cpu_stages_ms"]
        }
        row["load_before"] = min(r["load_before"] for r in same)
        row["load_after"] = max(r["load_after"] for r in same)
        merged.append(row)
    return merged


def _print_against_baseline(rows: list[dict], base: list[dict], rev: str) -> bool:
    """The speed-up table over the baseline revision and issue 24's targets; True if one is missed."""
    print(f"against the baseline {rev} (same run, alternating; medians over rounds):")
    print(
        "| scene | threads | fwd | fwd FPS | baseline fwd | speed-up | fwd+bwd | baseline fwd+bwd | "
        "speed-up | load |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    failed = False
    for r, b in zip(rows, base, strict=True):
        fwd, bfwd = r["cpu_fwd"]["median_s"], b["cpu_fwd"]["median_s"]
        fb, bfb = r["cpu_fwdbwd"]["median_s"], b["cpu_fwdbwd"]["median_s"]
        print(
            f"| {r['n'] // 1000}k Gaussians {r['size']}x{r['size']} | {r['threads']} | {_fmt_ms(fwd)} | "
            f"{1 / fwd:.1f} | {_fmt_ms(bfwd)} | {bfwd / fwd:.2f}x | {_fmt_ms(fb)} | {_fmt_ms(bfb)} | "
            f"{bfb / fb:.2f}x | {min(r['load_before'], b['load_before']):.1f}-"
            f"{max(r['load_after'], b['load_after']):.1f} |"
        )
    for r in rows:
        target = LIVE_TARGETS.get((r["n"], r["size"], str(r["threads"])))
        if target is not None:
            fps = 1 / r["cpu_fwd"]["median_s"]
            ok = fps >= target
            failed |= not ok
            print(f"target {r['n']}@{r['size']} threads={r['threads']}: forward {fps:.1f} FPS >= {target:g} "
                  f"{'OK' if ok else 'MISSED'} (issue 24)")  # fmt: skip
    print()
    return failed


if __name__ == "__main__":
    sys.exit(main())
