"""``stg-eval``: score a trained run on its novel-view or novel-pose split, or both.

    stg-eval RUN_DIR --split novel_view|novel_pose|both [--data DIR] [--json] [--no-parts] [--light L]

The protocol (docs/METRICS.md, "full"): each view of the split rendered at the dataset's size on
black, against the masked ground truth over the whole image; PSNR, SSIM (11x11 Gaussian),
LPIPS (alex) averaged over views. Novel views are rendered at their own time with the refined
training pose; novel poses take the time code of the nearest training pose (docs/AVATAR.md).
With --json the last line of stdout is one JSON object. A side-by-side image of the first views
goes to RUN_DIR/eval_<split>.png. On a synthetic benchmark (stg-synth) the report adds the PSNR
per body part (from the ground-truth surface: stg_node.data.synth.body_parts) and the condition
the benchmark tests (its light, motions, and how far the held-out frames are from training in
pose and orientation); ``--split both`` scores the two splits and their gap (novel views minus
novel poses, dB). Every view with a true mask adds the spill (the rendered alpha beyond the true
silhouette, per body part on a synthetic benchmark: streaks off a limb), and the run's Gaussians
their shape (axis ratios) and skinning disagreement with their neighbours
(stg_node.avatar.shape_stats). ``--light`` renders an avatar with shading under another light than its
learned one (``baked``: the light turning with the body, for comparison; as stg-render). Exit
codes: 0 ok, 1 failed, 2 bad usage.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from stg_node.cli.runner import UsageError, add_log_level_option, run_main
from stg_node.threads import configure_threads


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="stg-eval", description="Score a trained STG-Avatar run on a test split."
    )
    p.add_argument("run", help="run folder written by stg-train")
    p.add_argument(
        "--split",
        required=True,
        choices=("novel_view", "novel_pose", "both"),
        help="test split (both: the two and their gap)",
    )
    p.add_argument("--data", default=None, help="dataset folder (default: the one the run trained on)")
    p.add_argument("--json", action="store_true", help="print one JSON object as the last line of stdout")
    p.add_argument(
        "--lpips", default="alex", help="LPIPS networks, comma-separated, or 'none' (default alex)"
    )
    p.add_argument(
        "--no-parts", action="store_true", help="skip the per-body-part scores of a synthetic benchmark"
    )
    p.add_argument(
        "--light",
        default="learned",
        help="light of an avatar with shading: learned (default), baked, albedo, 27 SH numbers, or JSON",
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
    from stg_node.avatar.shading import parse_light

    configure_threads(args.threads)
    try:
        args.light_spec = parse_light(getattr(args, "light", "learned"))
    except ValueError as exc:
        raise UsageError(str(exc)) from exc
    result = evaluate_run(args)
    if args.json:
        print(json.dumps(result))
        return 0
    for split in ("novel_view", "novel_pose"):
        scores = result.get(split, result if result["split"] == split else None)
        if scores is not None:
            print(_scores_text(split, scores))
    if "gap_db" in result:
        print(f"gap (novel views - novel poses): {result['gap_db']:+.2f} dB")
    any_scores = result.get("novel_view") or result.get("novel_pose") or result
    print(
        f"{any_scores['gaussians']} Gaussians, {100 * any_scores['active_motion_fraction']:.1f}% with "
        f"motion, {any_scores['model_mb']:.1f} MB [protocol: {any_scores['protocol']}]"
    )
    condition = result.get("condition")
    if condition:
        print(_condition_text(condition))
    shape = any_scores.get("shape")
    if shape:
        print(_shape_text(shape))
    return 0


def _shape_text(shape: dict) -> str:
    def p(d: dict, fmt: str) -> str:
        return " / ".join(format(d[k], fmt) for k in ("p50", "p90", "p99"))

    return (
        "Gaussian shape (p50 / p90 / p99): largest/smallest axis "
        f"{p(shape['scale_ratio'], '.1f')}, largest/middle {p(shape['needle_ratio'], '.2f')}; skinning "
        f"disagreement with neighbours {p(shape['skin_disagreement'], '.3f')} (the body's "
        f"{p(shape['body_skin_disagreement'], '.3f')})"
    )


def _scores_text(split: str, r: dict) -> str:
    text = (
        f"{split}: PSNR {r['psnr']:.2f} dB, SSIM {r['ssim']:.4f}, LPIPS {r['lpips']:.4f} "
        f"over {r['images']} views"
    )
    if r.get("parts"):
        text += "\n  per body part (PSNR, dB): " + ", ".join(
            f"{name} {value:.2f}" for name, value in r["parts"].items()
        )
    spill = r.get("spill")
    if spill:
        text += (
            f"\n  spill (alpha beyond the true silhouette + {spill['margin_px']:g} px, % of its area): "
            f"{spill['spill_pct']:.2f}"
        )
        if spill["regions"]:
            text += (
                " ("
                + ", ".join(f"{name} {value['spill_pct']:.2f}" for name, value in spill["regions"].items())
                + ")"
            )
    return text


def _condition_text(c: dict) -> str:
    text = f"benchmark: {c['shading']} light, trained on {c['motion']}"
    if c.get("test_motion"):
        text += f", held-out frames {'/'.join(c['test_motion'])}"
    if c.get("train_yaw_deg") is not None:
        text += f", training orientations within {c['train_yaw_deg']:.0f} deg"
    if c.get("test_yaw_deg") is not None:
        text += f", held-out ones turned {c['test_yaw_deg']:.0f} deg"
    held = c.get("held_out")
    if held and held["frames"]:
        text += (
            f"\n  held-out poses: {held['pose_rms_deg']['median']:.1f} deg (RMS over the joints) from the "
            f"nearest training pose, {held['orientation_deg']['median']:.1f} deg from the nearest training "
            "orientation (medians)"
        )
    return text


def evaluate_run(args) -> dict:
    """Scores of ``args.split`` (one split's dict), or of both splits with their gap."""
    from stg_node.avatar.loading import load_run_renderer

    loaded = load_run_renderer(
        Path(args.run), device=args.device, backend=args.backend, light=getattr(args, "light_spec", None)
    )
    spec = loaded[0].data_spec()
    if args.data:
        spec = spec.with_root(Path(args.data).resolve())
    labeller = None
    if spec.format == "synthetic" and not getattr(args, "no_parts", False):
        from stg_node.data.synth.body_parts import SynthPartLabeller

        labeller = SynthPartLabeller(spec.root)
    if args.split != "both":
        return _evaluate_split(args, args.split, loaded, spec, labeller)
    out: dict = {"split": "both"}
    for split in ("novel_view", "novel_pose"):
        out[split] = _evaluate_split(args, split, loaded, spec, labeller)
    out["gap_db"] = out["novel_view"]["psnr"] - out["novel_pose"]["psnr"]
    if "condition" in out["novel_pose"]:
        out["condition"] = out["novel_pose"]["condition"]
    return out


def _evaluate_split(args, split: str, loaded, spec, labeller) -> dict:
    import math

    from stg_node.avatar.evaluate import evaluate_split, save_comparison
    from stg_node.avatar.shape_stats import shape_stats
    from stg_node.avatar.snapshot import model_nbytes

    run, renderer, corrections, summary = loaded
    dataset = spec.open(split)
    nets = () if args.lpips == "none" else tuple(n for n in args.lpips.split(",") if n)
    report, kept = evaluate_split(
        renderer,
        dataset,
        split=split,
        lpips_nets=nets,
        pose_corrections=corrections if split == "novel_view" else None,
        show_progress=not args.no_progress,
        keep_images=6,
        regions=None if labeller is None else labeller.regions,
    )
    if kept:
        save_comparison(kept, run.path / f"eval_{split}.png")
    lpips = report["lpips"].get(nets[0], math.nan) if nets else math.nan
    model = renderer.model
    active = float(model.table.motion_active().float().mean()) if model.table.num else 0.0
    result = {
        "split": split,
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
    if "regions" in report:
        result["parts"] = {name: value["psnr"] for name, value in report["regions"].items()}
    if "spill" in report:
        result["spill"] = report["spill"]
    result["shape"] = shape_stats(model).to_dict()
    if spec.format == "synthetic":
        from stg_node.data.synth.split_distances import benchmark_condition
        from stg_node.data.synth.writer import read_metadata

        frames = sorted({int(f) for f in dataset.frames}) if split == "novel_pose" else None
        result["condition"] = benchmark_condition(read_metadata(Path(spec.root)), frames)
    return result


if __name__ == "__main__":
    sys.exit(main())
