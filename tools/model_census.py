#!/usr/bin/env python3
"""What a trained avatar's Gaussians are, against what its training views resolve (docs/BENCHMARKS.md).

Per run folder (stg-train's layout: ``checkpoint.stgsnap``), from the model and the densification
strategy's state: each Gaussian's largest standard deviation over the pixel footprint it was seen at
(``m_per_px``, the running mean of depth / focal length), and the share of Gaussians whose nearest
neighbour in the canonical space is closer than ``--near-mm`` (clones that never separated from
their source render as one Gaussian). With ``--weights``, also what each Gaussian contributes to its
own training views: its blend weight (alpha times transmittance) summed over every pixel of every
training view, read as the gradient of a rendered channel of ones, and the largest in any one view.

    python tools/model_census.py runs/r8/runs/still_auto runs/r8/runs/auto
    python tools/model_census.py --weights runs/r9x/runs/still_auto runs/r9x/runs/auto
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def blend_weights(run: Path) -> tuple[np.ndarray, np.ndarray]:
    """(summed, largest) blend weight of each Gaussian over the run's training views, in pixels."""
    import json

    import torch

    from stg_node.avatar.data_spec import DataSpec
    from stg_node.avatar.loading import corrected, load_run_renderer
    from stg_node.avatar.model import BodyState, Camera3
    from stg_node.splat.api import rasterize

    data = json.loads((run / "config.json").read_text())["data"]
    spec = DataSpec(data["root"], data["format"], size=data["size"])
    _, renderer, corrections, _ = load_run_renderer(run)
    n = renderer.model.table.num
    total, peak = np.zeros(n), np.zeros(n)
    for sample in spec.open("train"):
        smpl = corrected(sample.smpl, corrections.get(sample.index))
        cam = Camera3.from_camera(sample.camera, device=renderer.device)
        with torch.no_grad():
            body = BodyState.from_smpl(smpl, renderer.device)
            posed = renderer.model.pose(body, renderer.time_for(smpl, sample.time), cam.center)
        ones = torch.ones(posed.means.shape[0], 1, requires_grad=True)
        image, _, _ = rasterize(
            posed.means, posed.quats, posed.scales, posed.opacities, ones, cam.viewmat, cam.K,
            cam.width, cam.height, backend=renderer.backend,
        )  # fmt: skip
        image.sum().backward()  # d(sum of pixels)/d(row's value) = its blend weights, summed
        weight = ones.grad[:, 0].double().numpy()
        rows = np.arange(n) if posed.index is None else posed.index.numpy()
        total[rows] += weight
        peak[rows] = np.maximum(peak[rows], weight)
    return total, peak


def main() -> None:
    from scipy.spatial import cKDTree

    from stg_node.avatar.checkpoint import load

    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("runs", nargs="+", type=Path, help="run folders (checkpoint.stgsnap)")
    parser.add_argument("--near-mm", type=float, default=1.0)
    parser.add_argument("--weights", action="store_true", help="also each Gaussian's blend weight (renders)")
    args = parser.parse_args()
    print(
        "| run | Gaussians | largest std / pixel footprint, quartiles | under 1 px | "
        f"nearest neighbour < {args.near_mm:g} mm | median footprint |"
    )
    print("|---|---|---|---|---|---|")
    for run in args.runs:
        state = load(run / "checkpoint.stgsnap")
        table = state.model.table
        largest = table.scales().detach().max(dim=1).values.numpy()
        footprint = state.densify.get("m_per_px")
        if footprint is None or footprint.shape[0] != largest.shape[0]:
            raise SystemExit(f"{run}: its checkpoint keeps no per-Gaussian pixel footprint (m_per_px)")
        footprint = footprint.numpy()
        seen = footprint > 0
        ratio = largest[seen] / footprint[seen]
        means = table["means"].detach().numpy()
        nearest = cKDTree(means).query(means, k=2)[0][:, 1]
        q = np.percentile(ratio, [25, 50, 75])
        print(
            f"| {run} | {largest.shape[0]:,} | {q[0]:.2f} / {q[1]:.2f} / {q[2]:.2f} | "
            f"{100 * (ratio < 1).mean():.1f} % | {100 * (nearest < args.near_mm / 1000).mean():.1f} % | "
            f"{1000 * np.median(footprint[seen]):.2f} mm |"
        )
        if args.weights:
            total, peak = blend_weights(run)
            ranked = np.cumsum(np.sort(total)[::-1]) / total.sum()
            holding = (int(np.searchsorted(ranked, 0.999)) + 1) / total.size
            print(
                f"|   {run}: blend weight | never above 0.1 px in a training view: "
                f"{100 * (peak < 0.1).mean():.1f} % | summed median {np.median(total):.1f} px | "
                f"99.9 % of all weight held by {100 * holding:.1f} % of the Gaussians | | |"
            )


if __name__ == "__main__":
    main()
