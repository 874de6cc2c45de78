"""``stg-eval``: score a trained run on its novel-view or novel-pose split.

    stg-eval RUN_DIR --split novel_view|novel_pose [--data DIR] [--json]

The protocol (docs/METRICS.md, "full"): each view of the split rendered at the dataset's size on
black, against the masked ground truth over the whole image; PSNR, SSIM (11x11 Gaussian),
LPIPS (alex) averaged over views. Novel views are rendered at their own time with the refined
training pose; novel poses take the time code of the nearest training pose (docs/AVATAR.md).
With --json the last line of stdout is one JSON object. A side-by-side image of the first views
goes to RUN_DIR/eval_<split>.png. Exit codes: 0 ok, 1 failed, 2 bad usage.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from stg_node.cli.runner import add_log_level_option, run_main
from stg_node.threads import configure_threads


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="stg-eval", description="Score a trained STG-Avatar run on a test split."
    )
    p.add_argument("run", help="run folder written by stg-train")
    p.add_argument("--split", required=True, choices=("novel_view", "novel_pose"), help="test split")
    p.add_argument("--data", default=None, help="dataset folder (default: the one the run trained on)")
    p.add_argument("--json", action="store_true", help="print one JSON object as the last line of stdout")
    p.add_argument(
        "--lpips", default="alex", help="LPIPS networks, comma-separated, or 'none' (default alex)"
    )
    p.add_argument("--backend", default="auto", choices=("auto", "cpu", "cuda", "torch"))
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", default=None, help="CPU threads (default: STG_THREADS or 1)")
    p.add_argument("--no-progress", action="store_true")
    add_log_level_option(p)
    return p


def main(argv: list[str] | None = None) -> int:
    from stg_node.avatar.snapshot import SnapshotError
    from stg_node.data.errors import DatasetError

    return run_main(build_parser(), run, argv, expected=(DatasetError, SnapshotError))


def run(args: argparse.Namespace) -> int:
    configure_threads(args.threads)
    result = evaluate_run(args)
    if args.json:
        print(json.dumps(result))
    else:
        print(
            f"{args.split}: PSNR {result['psnr']:.2f} dB, SSIM {result['ssim']:.4f}, "
            f"LPIPS {result['lpips']:.4f} "
            f"over {result['images']} views; {result['gaussians']} Gaussians, "
            f"{100 * result['active_motion_fraction']:.1f}% with motion, {result['model_mb']:.1f} MB\n"
            f"[protocol: {result['protocol']}]"
        )
    return 0


def evaluate_run(args) -> dict:
    import math

    from stg_node.avatar.evaluate import evaluate_split, save_comparison
    from stg_node.avatar.loading import load_run_renderer

    run, renderer, corrections, summary = load_run_renderer(
        Path(args.run), device=args.device, backend=args.backend
    )
    spec = run.data_spec()
    if args.data:
        spec = spec.with_root(Path(args.data).resolve())
    dataset = spec.open(args.split)
    nets = () if args.lpips == "none" else tuple(n for n in args.lpips.split(",") if n)
    report, kept = evaluate_split(
        renderer,
        dataset,
        split=args.split,
        lpips_nets=nets,
        pose_corrections=corrections if args.split == "novel_view" else None,
        show_progress=not args.no_progress,
        keep_images=6,
    )
    if kept:
        save_comparison(kept, run.path / f"eval_{args.split}.png")
    lpips = report["lpips"].get(nets[0], math.nan) if nets else math.nan
    model = renderer.model
    active = float(model.table.motion_active().float().mean()) if model.table.num else 0.0
    from stg_node.avatar.snapshot import model_nbytes

    return {
        "split": args.split,
        "psnr": report["psnr"],
        "ssim": report["ssim"],
        "lpips": lpips,
        "lpips_unavailable": report["lpips_unavailable"],
        "images": report["views"],
        "gaussians": model.table.num,
        "active_motion_fraction": active,
        "model_mb": model_nbytes(model) / 1e6,
        "train_seconds": summary.get("train_seconds", math.nan),
        "render_ms": report["render_ms_mean"],
        "protocol": report["protocol"],
    }


if __name__ == "__main__":
    sys.exit(main())
