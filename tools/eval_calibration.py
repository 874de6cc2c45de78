#!/usr/bin/env python3
"""Accuracy of stg-calibrate on synthetic ChArUco captures with known truth (docs/RIGS.md).

For each seed: a ring of cameras with varied focal lengths, principal points and lens distortion
(stg_node.calibration.synthetic), a capture like a careful user's (close-ups in front of each
camera, then the board moving in the middle, turned between neighbouring cameras), rendered
through each lens with sensor noise; detection and calibration as stg-calibrate runs them; the
result compared with the truth after the best rigid alignment (the world frame is a choice).
Baseline, same detections, same run: the calibration without its joint refinement (each camera's
own OpenCV calibration, the extrinsics chained through the shared sightings).

    python tools/eval_calibration.py [--cameras 4 --size 640x480 --radius 2.5 --instants 80
                                      --close-ups 30 --seeds 1,2,3] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's stg_node first


def main(argv: list[str] | None = None) -> int:
    from stg_node.logs import configure_logging
    from stg_node.threads import configure_threads

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cameras", type=int, default=4)
    parser.add_argument("--size", default="640x480")
    parser.add_argument("--radius", type=float, default=2.5, help="metres from the middle")
    parser.add_argument("--instants", type=int, default=80, help="board poses in the middle")
    parser.add_argument("--close-ups", type=int, default=30, help="board poses close in front of each camera")
    parser.add_argument("--seeds", default="1,2,3")
    parser.add_argument("--board", default="9x6")
    parser.add_argument("--square", type=float, default=0.07)
    parser.add_argument("--marker", type=float, default=0.052)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    configure_logging()
    threads = configure_threads()

    import numpy as np

    from stg_node.calibration.board import BoardDetector, BoardSpec, parse_board_size
    from stg_node.calibration.solve import calibrate_rig
    from stg_node.calibration.synthetic import rig_errors, ring_rig, synthetic_capture

    width, height = (int(v) for v in args.size.lower().split("x"))
    spec = BoardSpec(*parse_board_size(args.board), args.square, args.marker)
    detector = BoardDetector(spec)
    rows = []
    for seed in (int(s) for s in args.seeds.split(",")):
        rig = ring_rig(args.cameras, size=(width, height), radius=args.radius, seed=seed)
        capture = synthetic_capture(rig, spec, args.instants, seed=seed + 10, close_ups=args.close_ups)
        started = time.perf_counter()
        detections = [[detector(image) for image in views] for views in capture.images]
        detected = time.perf_counter()
        result = calibrate_rig(rig.names, [c.image_size for c in rig.cameras], detections, spec)
        solved = time.perf_counter()
        chained = calibrate_rig(
            rig.names, [c.image_size for c in rig.cameras], detections, spec, joint_refinement=False
        )
        row = {"seed": seed, "detect_s": detected - started, "solve_s": solved - detected}
        for key, found in (("joint", result), ("chained", chained)):
            errors = rig_errors(found.rig, rig)
            row[key] = {
                "rms_px": [round(r.rms_px, 4) for r in found.reports],
                "centre_mm": [round(1000 * c, 2) for c, _ in errors],
                "rotation_deg": [round(a, 4) for _, a in errors],
                "focal_error_pct": [
                    round(100 * abs(e.K[0, 0] - t.K[0, 0]) / t.K[0, 0], 3)
                    for e, t in zip(found.rig.cameras, rig.cameras, strict=True)
                ],
            }
        row["views"] = [r.views for r in result.reports]
        rows.append(row)
        for key in ("joint", "chained"):
            r = row[key]
            print(
                f"seed {seed} {key:7s}: RMS {max(r['rms_px']):.3f} px (worst camera), centres within "
                f"{max(r['centre_mm']):.1f} mm, rotations within {max(r['rotation_deg']):.3f} deg, "
                f"focal lengths within {max(r['focal_error_pct']):.2f} %"
            )
        print(
            f"seed {seed}: detection {row['detect_s']:.1f} s, calibration {row['solve_s']:.1f} s for "
            f"{len(capture.images)} instants x {args.cameras} cameras"
        )
    worst = {
        key: {name: max(max(r[key][name]) for r in rows) for name in ("rms_px", "centre_mm", "rotation_deg")}
        for key in ("joint", "chained")
    }
    for key in ("joint", "chained"):
        w = worst[key]
        print(
            f"worst over seeds, {key}: RMS {w['rms_px']:.3f} px, centres {w['centre_mm']:.1f} mm, rotations "
            f"{w['rotation_deg']:.3f} deg (targets 0.5 px, 10 mm, 0.5 deg)"
        )
    print(
        f"centre error, chained / joint: {worst['chained']['centre_mm'] / worst['joint']['centre_mm']:.1f}x; "
        f"{threads} thread(s), {platform.processor() or platform.machine()}"
    )
    if args.json is not None:
        args.json.write_text(json.dumps({"args": vars(args) | {"json": str(args.json)}, "seeds": rows,
                                         "worst": worst}, indent=1, default=str) + "\n")  # fmt: skip
    return 0 if np.isfinite(worst["joint"]["rms_px"]) else 1


if __name__ == "__main__":
    sys.exit(main())
