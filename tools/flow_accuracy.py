#!/usr/bin/env python3
"""How far the optical flow the trainer reads is from the true motion, per DIS setting (docs/BENCHMARKS.md).

Every threshold that reads the flow (the trial's missed-motion test, the motion gates, the flow-guided
seeds) is in pixels of the frames, so the flow's own error in those pixels decides what they can
tell apart. A synthetic subject knows its true flow (``stg_node.data.synth.true_flow``); this tool
compares ``stg_node.data.flow.compute_flow_pair`` with it on the training camera's consecutive frames
(every ``--every``-th pair), over the body's pixels where the flow passed its forward-backward check.

    python tools/flow_accuracy.py --subject still --scale medium --data-cache runs/flow_accuracy
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import tradeoff  # noqa: E402

# (label, preset, finest_scale): None is the preset's own finest level
VARIANTS = (
    ("DIS fast, level 2 (the preset's)", "fast", None),
    ("DIS fast, level 1", "fast", 1),
    ("DIS fast, level 0 (default)", "fast", 0),
    ("DIS medium (its level 1)", "medium", None),
)


def errors(samples, truth_of, settings) -> tuple[np.ndarray, np.ndarray]:
    """|flow - true flow| and |true flow| (px) over the valid body pixels of consecutive pairs."""
    from stg_node.data.flow import compute_flow_pair

    err, motion = [], []
    for a, b in samples:
        truth = truth_of(a)
        pair = compute_flow_pair(a.image, b.image, a.mask, b.mask, settings)
        seen = truth.covered & pair.valid_forward
        err.append(np.linalg.norm(pair.forward - truth.flow, axis=-1)[seen])
        motion.append(truth.magnitude[seen])
    return np.concatenate(err), np.concatenate(motion)


def main() -> None:
    from stg_node.avatar.data_spec import DataSpec
    from stg_node.body import load_body_model
    from stg_node.data.flow import FlowSettings
    from stg_node.data.synth.true_flow import benchmark_true_flow
    from stg_node.data.synth.writer import read_metadata
    from stg_node.threads import configure_threads

    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--subject", default="still", choices=sorted(tradeoff.SUBJECTS))
    parser.add_argument("--scale", default="medium", choices=("medium", "full"))
    parser.add_argument("--data-cache", type=Path, default=Path("runs/flow_accuracy"))
    parser.add_argument("--every", type=int, default=6, help="every K-th training pair")
    parser.add_argument("--threshold-px", type=float, default=None, help="default: 1.5 px at 512, scaled")
    args = parser.parse_args()
    configure_threads(None)
    import bench_nonrigid

    scale = bench_nonrigid.SCALES[args.scale]
    threshold = args.threshold_px if args.threshold_px is not None else 1.5 * scale.size / 512
    folder = tradeoff.ensure_subject(args.data_cache, args.subject, scale)
    meta = read_metadata(folder)
    faces = load_body_model().faces.cpu().numpy()
    frames = list(DataSpec(str(folder), "synthetic", size=scale.size).open("train"))
    pairs = [(a, b) for a, b in zip(frames[:-1], frames[1:], strict=True) if b.index == a.index + 1][
        :: max(args.every, 1)
    ]
    cuts = tuple((meta.get("held_out") or {}).get("cuts", ()))

    def truth_of(sample):
        return benchmark_true_flow(
            folder, sample.index, sample.camera, faces, int(meta["num_frames"]), cuts=cuts
        )

    print(f"# {args.subject}, {scale.size} px, {len(pairs)} pairs; share above {threshold:g} px")
    print("| flow | true motion, mean | error, mean | error, median | share above threshold |")
    print("|---|---|---|---|---|")
    for label, preset, level in VARIANTS:
        err, motion = errors(pairs, truth_of, FlowSettings(preset=preset, finest_scale=level))
        print(
            f"| {label} | {motion.mean():.2f} px | {err.mean():.2f} px | {np.median(err):.2f} px | "
            f"{100 * (err > threshold).mean():.1f} % |"
        )


if __name__ == "__main__":
    main()
