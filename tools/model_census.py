#!/usr/bin/env python3
"""What a trained avatar's Gaussians are, against what its training views resolve (docs/BENCHMARKS.md).

Per run folder (stg-train's layout: ``checkpoint.stgsnap``), from the model and the densification
strategy's state: each Gaussian's largest standard deviation over the pixel footprint it was seen at
(``m_per_px``, the running mean of depth / focal length), and the share of Gaussians whose nearest
neighbour in the canonical space is closer than ``--near-mm`` (clones that never separated from
their source render as one Gaussian).

    python tools/model_census.py runs/r8/runs/still_auto runs/r8/runs/auto
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    from scipy.spatial import cKDTree

    from stg_node.avatar.checkpoint import load

    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("runs", nargs="+", type=Path, help="run folders (checkpoint.stgsnap)")
    parser.add_argument("--near-mm", type=float, default=1.0)
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


if __name__ == "__main__":
    main()
