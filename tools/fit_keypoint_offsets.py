#!/usr/bin/env python3
"""Measure where a keypoint detector's points sit relative to the SMPL points its layout names.

Generates synthetic sequences with four cameras around the subject (stg-synth, other seeds and
motions than the tracking benchmark: tools/eval_track.py uses seed 0), runs the detector on
every view, triangulates the keypoints and takes, per fit target, the median offset from the
true SMPL point in the rest axes of the bone it moves with
(:func:`measure_offsets`). Prints the table to paste into
``OFFSETS`` in stg_node/tracking/keypoint_offsets.py, with each offset's spread.

    python tools/fit_keypoint_offsets.py [--frames 90 --size 512 --seeds 11,12,13 --motions dance,walk,turn]
                                         [--data-cache DIR] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's stg_node first


def measure_offsets(body, layout, projections, keypoints, truths, min_score: float = 0.3):
    """Median offsets of triangulated keypoints from the layout's SMPL points, in carrier axes.

    ``projections`` (V, 3, 4) of the cameras; ``keypoints[frame][view]`` detections (or None);
    ``truths[frame]``: (poses (24, 3), Rh, Th, betas) of the true body. Returns target name ->
    (carrier joint name, (3,) median offset, frames used, median distance after the correction).
    """
    import numpy as np
    import torch

    from stg_node.body import lbs
    from stg_node.body.smpl_io import SMPL_JOINT_NAMES
    from stg_node.tracking.body_points import BodyKeypoints
    from stg_node.tracking.keypoint_offsets import carrier
    from stg_node.tracking.multiview_fit import triangulate

    model = BodyKeypoints(body, [t.point for t in layout.targets]).double()
    parents = body.parents.tolist()
    carriers = [carrier(layout, t, parents) for t in range(len(layout.targets))]
    local = [[] for _ in layout.targets]
    for row, (poses, Rh, Th, betas) in zip(keypoints, truths, strict=True):
        views = len(row)
        xy = np.zeros((views, len(layout.targets), 2))
        weight = np.zeros((views, len(layout.targets)))
        for v, found in enumerate(row):
            if found is None:
                continue
            for t, target in enumerate(layout.targets):
                xy[v, t] = np.asarray(found.xy)[list(target.sources)].mean(axis=0)
                weight[v, t] = min(float(found.score[s]) for s in target.sources)
        weight[weight < min_score] = 0.0
        points = triangulate(projections, xy, weight).points
        with torch.no_grad():
            pose = torch.as_tensor(np.asarray(poses, np.float64).reshape(1, 24, 3))
            rotations = lbs.axis_angle_to_matrix(pose.clone())
            rotations[:, 0] = torch.eye(3, dtype=torch.float64)
            shaped = torch.as_tensor(np.asarray(betas, np.float64).reshape(1, -1))
            _, bones = lbs.rigid_chain(rotations, model.rest_joints(shaped), model.parents)
            true = model(
                shaped, pose[:, 1:], torch.as_tensor(Rh).reshape(1, 3), torch.as_tensor(Th).reshape(1, 3)
            )
        root = lbs.axis_angle_to_matrix(torch.as_tensor(np.asarray(Rh, np.float64))).numpy()
        true = true[0].numpy()
        for t in range(len(layout.targets)):
            if np.all(np.isfinite(points[t])):
                rotation = root @ bones[0, carriers[t], :3, :3].numpy()
                local[t].append(rotation.T @ (points[t] - true[t]))
    out = {}
    for t, target in enumerate(layout.targets):
        if not local[t]:
            continue
        values = np.asarray(local[t])
        median = np.median(values, axis=0)
        out[target.point.name] = (
            SMPL_JOINT_NAMES[carriers[t]],
            median,
            len(values),
            float(np.median(np.linalg.norm(values - median, axis=1))),
        )
    return out


def main(argv: list[str] | None = None) -> int:
    from stg_node.logs import configure_logging
    from stg_node.threads import configure_threads

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=90)
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--seeds", default="11,12,13")
    parser.add_argument("--motions", default="dance,walk,turn")
    parser.add_argument("--detector", default="blazepose")
    parser.add_argument("--data-cache", type=Path, default=Path("runs/keypoint_offsets"))
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    configure_logging()
    configure_threads()

    import numpy as np

    from stg_node.body import load_body_model
    from stg_node.data.io import read_image
    from stg_node.data.synth import SynthConfig, generate
    from stg_node.data.synth.writer import read_metadata
    from stg_node.safe_load import load_npy
    from stg_node.tracking.detectors import make_detector
    from stg_node.tracking.layouts import get_layout
    from stg_node.tracking.rig_evaluation import synth_rig

    seeds = [int(s) for s in args.seeds.split(",")]
    motions = args.motions.split(",")
    if len(seeds) != len(motions):
        parser.error("--seeds and --motions need the same count")
    cameras = ["1", "3", "5", "7"]  # four of a ring of eight, 90 degrees apart
    body = load_body_model()
    keypoints, truths, projections = [], [], None
    layout = None
    pooled: dict[str, list] = {}
    for seed, motion in zip(seeds, motions, strict=True):
        folder = args.data_cache / f"{motion}_s{seed}_{args.frames}f_{args.size}px"
        try:
            read_metadata(folder)
        except (FileNotFoundError, ValueError):
            generate(
                SynthConfig(
                    out=folder,
                    seed=seed,
                    num_frames=args.frames,
                    size=args.size,
                    motion=motion,
                    num_novel_views=7,
                    view_every=1000,
                    train_cameras=tuple(int(c) - 1 for c in cameras),
                    overwrite=True,
                ),
                progress=False,
            )
        rig = synth_rig(folder, cameras)
        projections = np.stack([c.K @ np.column_stack([c.R, c.t]) for c in rig.cameras])
        detectors = [make_detector(args.detector) for _ in cameras]
        layout = get_layout(detectors[0].layout)
        keypoints, truths = [], []
        for i in range(args.frames):
            keypoints.append(
                [
                    d(read_image(folder / f"Camera_B{c}" / f"{i:06d}.png"))
                    for d, c in zip(detectors, cameras, strict=True)
                ]
            )
            p = load_npy(folder / "new_params" / f"{i}.npy")
            truths.append(
                (p["poses"].reshape(24, 3), p["Rh"].reshape(3), p["Th"].reshape(3), p["shapes"].reshape(-1))
            )
        for name, (carrier, offset, count, spread) in measure_offsets(
            body, layout, projections, keypoints, truths
        ).items():
            pooled.setdefault(name, []).append((carrier, offset, count, spread))
            print(
                f"{motion:6s} seed {seed}: {name:15s} {carrier:15s} {np.round(offset * 1000, 1)} mm "
                f"({count} frames, spread {spread * 1000:.1f} mm)"
            )
    table = {}
    print(f'\n    "{layout.name}": {{')
    for name, rows in pooled.items():
        carrier = rows[0][0]
        weights = np.array([r[2] for r in rows], dtype=np.float64)
        offset = (np.stack([r[1] for r in rows]) * weights[:, None]).sum(0) / weights.sum()
        between = max(float(np.linalg.norm(r[1] - offset)) for r in rows)
        table[name] = (carrier, [round(float(v), 4) for v in offset])
        values = ", ".join(f"{v:.4f}" for v in offset)
        print(
            f'        "{name}": ("{carrier}", ({values})),  # sequences differ by <= {between * 1000:.0f} mm'
        )
    print("    },")
    if args.json is not None:
        args.json.write_text(json.dumps({layout.name: table}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
