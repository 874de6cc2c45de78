#!/usr/bin/env python3
"""Time optical flow for one 512x512 frame pair as the trainer computes it (docs/BENCHMARKS.md).

The pair imitates a delivered ZJU-MoCap frame: a textured person-shaped region (about a third of
the image) on a black background, moved by a small rotation and translation. Each variant
computes forward + backward flow and the consistency masks (stg_node.data.flow); the baseline
is OpenCV Farneback doing the same two directions on the full frame, measured in the same run.

    python tools/bench_flow.py [--repeats 20] [--size 512]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's stg_node first


def make_pair(size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    noise = rng.normal(size=(size, size, 3))
    tex = cv2.GaussianBlur(noise, (0, 0), 1.5) + 0.5 * cv2.GaussianBlur(noise, (0, 0), 6.0)
    tex = ((tex - tex.min()) / (tex.max() - tex.min()) * 255).astype(np.uint8)
    mask = np.zeros((size, size), np.uint8)
    cv2.ellipse(mask, (size // 2, size // 2), (size // 7, size * 2 // 5), 0, 0, 360, 255, -1)
    matrix = cv2.getRotationMatrix2D((size / 2, size / 2), 1.5, 1.0)
    matrix[:, 2] += (3.0, -2.0)
    tex_b = cv2.warpAffine(tex, matrix, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    mask_b = cv2.warpAffine(mask, matrix, (size, size), flags=cv2.INTER_NEAREST)
    a = np.where(mask[..., None] > 0, tex, 0).astype(np.uint8)
    b = np.where(mask_b[..., None] > 0, tex_b, 0).astype(np.uint8)
    return a, b, mask, mask_b


def median_ms(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times) * 1e3


def main() -> None:
    from stg_node.data.flow import FlowSettings, compute_flow_pair
    from stg_node.logs import configure_logging
    from stg_node.threads import configure_threads

    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--threads", default=None)
    args = parser.parse_args()
    configure_logging()
    threads = configure_threads(args.threads)
    a, b, ma, mb = make_pair(args.size)
    ga, gb = cv2.cvtColor(a, cv2.COLOR_RGB2GRAY), cv2.cvtColor(b, cv2.COLOR_RGB2GRAY)

    def farneback():
        cv2.calcOpticalFlowFarneback(ga, gb, None, 0.5, 3, 15, 3, 5, 1.2, 0)
        cv2.calcOpticalFlowFarneback(gb, ga, None, 0.5, 3, 15, 3, 5, 1.2, 0)

    variants = {"Farneback, full frame (baseline)": farneback}
    for preset in ("ultrafast", "fast", "medium"):  # each down to its preset's finest level
        cropped = FlowSettings(preset=preset, finest_scale=None)
        whole = FlowSettings(preset=preset, crop_margin=10**6, finest_scale=None)
        variants[f"DIS {preset}, person crop"] = lambda s=cropped: compute_flow_pair(a, b, ma, mb, s)
        variants[f"DIS {preset}, full frame"] = lambda s=whole: compute_flow_pair(a, b, ma, mb, s)
    for level in (1, 0):  # the fast preset down to half resolution, and to the frames' own (the default)
        settings = FlowSettings(finest_scale=level)
        default = " (default)" if settings == FlowSettings() else ""
        label = f"DIS fast to level {level}, person crop{default}"
        variants[label] = lambda s=settings: compute_flow_pair(a, b, ma, mb, s)
    from stg_node.data.flow import _crop_box, dis_flow

    x0, y0, x1, y1 = _crop_box(ma, mb, FlowSettings().crop_margin)
    ca, cb = np.ascontiguousarray(ga[y0:y1, x0:x1]), np.ascontiguousarray(gb[y0:y1, x0:x1])
    variants["DIS fast, person crop, both flows only (no consistency)"] = lambda: (
        dis_flow(ca, cb, "fast"),
        dis_flow(cb, ca, "fast"),
    )
    results = {name: median_ms(fn, args.repeats) for name, fn in variants.items()}
    base = results["Farneback, full frame (baseline)"]
    print(
        f"# {args.size}x{args.size} pair, forward+backward+consistency, median of {args.repeats}, "
        f"{threads} thread(s), OpenCV {cv2.__version__}, {platform.processor() or platform.machine()}"
    )
    print("| variant | ms per pair | speed vs Farneback |")
    print("|---|---|---|")
    for name, ms in results.items():
        print(f"| {name} | {ms:.1f} | {base / ms:.2f}x |")


if __name__ == "__main__":
    main()
