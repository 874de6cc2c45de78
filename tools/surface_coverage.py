#!/usr/bin/env python3
"""How much of a benchmark subject's surface its training views ever show (docs/BENCHMARKS.md).

Surface no training view shows has no detail to learn, so a subject's need for Gaussians depends on
how much of it is observed: a near-still subject that never turns shows one side, a dancer all of
them. This tool measures it from the benchmark's truth (``stg_node.data.synth.coverage``): the
share of the rest body's area never visible to the training cameras, seen in at most two views, and
seen in at least a quarter of them. Beside it, how much the subject moves in the training views
(the benchmark's true flow on the body's pixels, at the training size): a subject that turns moves
in the image even when skinning explains all of it.

    python tools/surface_coverage.py --subject still dance mixed --scale medium
    python tools/surface_coverage.py --folder runs/still_facing          # any stg-synth output
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import tradeoff  # noqa: E402


def main() -> None:
    from stg_node.avatar.data_spec import DataSpec
    from stg_node.body import load_body_model
    from stg_node.data.synth.coverage import benchmark_coverage
    from stg_node.data.synth.garment_truth import rest_body
    from stg_node.data.synth.true_flow import benchmark_true_flow
    from stg_node.data.synth.writer import read_metadata
    from stg_node.threads import configure_threads

    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--subject", nargs="*", default=[], choices=sorted(tradeoff.SUBJECTS))
    parser.add_argument("--folder", nargs="*", type=Path, default=[], help="generated benchmarks")
    parser.add_argument("--scale", default="medium", choices=("medium", "full"))
    parser.add_argument("--data-cache", type=Path, default=Path("runs/surface_coverage"))
    parser.add_argument("--supersample", type=int, default=4, help="samples per pixel side")
    args = parser.parse_args()
    if not args.subject and not args.folder:
        parser.error("name at least one --subject or --folder")
    configure_threads(None)
    import bench_nonrigid

    scale = bench_nonrigid.SCALES[args.scale]
    folders = [tradeoff.ensure_subject(args.data_cache, s, scale) for s in args.subject] + list(args.folder)
    body = load_body_model()
    faces = body.faces.cpu().numpy()
    print(f"# training views, {args.supersample}x{args.supersample} samples a pixel; shares of the rest area")
    print(
        "| subject | motion, train yaw | size | views | never seen | in <= 2 views | in >= 25 % of views "
        "| true motion, median / mean px per frame | body pixels moving > 0.5 px |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for folder in folders:
        meta = read_metadata(folder)
        size = int(meta["size"][0])
        samples = list(DataSpec(str(folder), "synthetic", size=size).open("train"))
        rest, _ = rest_body(folder, body)
        cov = benchmark_coverage(folder, samples, faces, rest, args.supersample)
        yaw = (meta.get("held_out") or {}).get("train_yaw_deg")
        cuts = tuple((meta.get("held_out") or {}).get("cuts", ()))
        moved = []
        frames = int(meta["num_frames"])
        for sample in samples:
            flow = benchmark_true_flow(folder, sample.index, sample.camera, faces, frames, cuts)
            moved.append(flow.magnitude[flow.covered])
        moved = np.concatenate(moved)
        print(
            f"| {folder.name} | {meta['motion']}, {'full turn' if yaw is None else f'{yaw:g} deg'} | "
            f"{size} px | {cov.views} | {100 * cov.fraction_never_seen():.1f} % | "
            f"{100 * cov.fraction_seen_in_at_most(2):.1f} % | "
            f"{100 * cov.fraction_seen_in_at_least(0.25):.1f} % | "
            f"{np.median(moved):.2f} / {moved.mean():.2f} | {100 * (moved > 0.5).mean():.1f} % |"
        )


if __name__ == "__main__":
    main()
