"""tools/tradeoff.py: the grid it trains, the scaling of --quick, the Pareto front, the marked docs section,
and end to end: --quick produces the table and the plot with sane numbers (one configuration in the
default suite, the whole quick grid in the slow one)."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

import tradeoff  # noqa: E402
import tradeoff_report  # noqa: E402


def test_grid_holds_every_preset_and_ablation_the_issue_names():
    from stg_node.avatar import preset

    rows = {r.name: r for r in tradeoff.grid("fast")}
    assert len(rows) == len(tradeoff.grid("fast"))  # names are unique
    for p in ("fast", "balanced", "quality"):
        assert rows[f"preset_{p}"].group == "preset" and rows[f"preset_{p}"].changes == {}
    lbs = rows["lbs_only"].config(tradeoff.FULL)
    assert lbs.model.spacetime is False and lbs.densify.flow_guided is False
    assert rows["no_flow_densify"].config(tradeoff.FULL).densify.flow_guided is False
    assert rows["no_flow_densify"].config(tradeoff.FULL).model.spacetime is True
    assert rows["sh_color"].config(tradeoff.FULL).model.color == "sh"
    base = preset("fast")
    orders = {
        rows[f"n_p{k}"].alias_of or rows[f"n_p{k}"].config(tradeoff.FULL).model.motion_order for k in range(4)
    }
    assert orders == {0, 1, 3, "polynomial"} and base.model.motion_order == 2
    # The motion order ablations are of the per-Gaussian polynomials; the default shares motion bases.
    assert rows["polynomial"].config(tradeoff.FULL).model.n_p == 2 and base.model.n_b == 24
    assert rows["n_p3"].config(tradeoff.FULL).model.motion_basis == 0
    assert rows["forced_on"].config(tradeoff.FULL).nonrigid == "on" and base.nonrigid == "auto"
    assert (
        rows["n_q0"].config(tradeoff.FULL).model.rotation_order == 0
        and rows["n_q1"].alias_of == "preset_fast"
    )
    half, double = rows["budget_half"].config(tradeoff.FULL), rows["budget_double"].config(tradeoff.FULL)
    assert (half.model.num_gaussians, half.model.max_gaussians) == (6000, 15000)
    assert (double.model.num_gaussians, double.model.max_gaussians) == (24000, 60000)
    assert rows["still_fast"].subject == "still" and rows["still_fast"].preset == "fast"
    assert {r.subject for r in rows.values()} == {"dance", "still", "mixed", *tradeoff.CONDITIONS}
    assert set(tradeoff.CONDITIONS) <= set(tradeoff.SUBJECTS)
    assert base.model.normal_sign == "auto"
    for subject in ("room_turn_held_out", "env_turn_held_out", "flat_turn_held_out", "room_facing"):
        for suffix, sign in (("outward_normals", "outward"), ("camera_normals", "camera")):
            row = rows[f"{subject}_{suffix}"]
            assert row.config(tradeoff.FULL).model.normal_sign == sign and row.group == "normal_sign"
    # The sign's decision comes at the same share of the schedule at every scale.
    assert rows["preset_fast"].config(tradeoff.MID).normal_decide_iter == round(base.normal_decide_iter / 3)
    held = tradeoff.SUBJECTS["room_turn_held_out"]
    assert (held.shading, held.train_yaw_deg, held.test_yaw_deg) == ("room", 60.0, 150.0)
    standing = tradeoff.SUBJECTS["still_standing"]  # the issue-22 subject without the turntable
    assert standing.synth_options()["motion"] == "still" and standing.synth_options()["train_yaw_deg"] == 0.0
    assert tradeoff.subject_frames("room_new_motions", tradeoff.FULL) == (200, 0.5)
    assert tradeoff.subject_frames("dance", tradeoff.FULL) == (125, 0.8)
    for row in rows.values():
        row.config(tradeoff.QUICK).validate()
    with pytest.raises(ValueError, match="--base"):
        tradeoff.grid("turbo")


def test_quick_scaling_shrinks_schedules_budgets_and_pixel_sizes_alike():
    from stg_node.avatar import preset

    full = preset("balanced")
    quick = tradeoff.scaled(full, tradeoff.QUICK)
    assert quick.iterations == round(full.iterations / 25)
    assert quick.densify.start_iter == round(full.densify.start_iter / 25)
    assert quick.loss.warmup_iters == round(full.loss.warmup_iters / 25)
    assert quick.model.num_gaussians == round(full.model.num_gaussians / 10)
    assert quick.model.max_gaussians == round(full.model.max_gaussians / 10)
    assert math.isclose(quick.densify.motion_floor_px, full.densify.motion_floor_px * 96 / 512)
    assert quick.densify.region_px == 3 and quick.crop_margin_px == 3
    assert quick.model.color == full.model.color and quick.densify.flow_guided == full.densify.flow_guided
    assert tradeoff.scaled(full, tradeoff.FULL) is full
    assert math.isclose(tradeoff.QUICK.fast_threshold_px, 5.0 * 96 / 512)


def test_mid_scale_halves_the_images_and_budgets_and_thirds_the_schedule():
    from stg_node.avatar import preset

    full = preset("fast")
    mid = tradeoff.scaled(full, tradeoff.SCALES["mid"])
    assert (mid.iterations, mid.densify.start_iter) == (
        round(full.iterations / 3),
        round(full.densify.start_iter / 3),
    )
    assert mid.model.max_gaussians == round(full.model.max_gaussians / 2)
    assert math.isclose(mid.densify.motion_floor_px, full.densify.motion_floor_px / 2)
    assert tradeoff.SCALES["mid"].size == 256 and tradeoff.SCALES["quick"] is tradeoff.QUICK


def test_scaling_a_config_that_predates_a_key_scales_the_keys_it_has():
    """A baseline tree (tools/baseline.py) is scaled with this tree's key lists: a key its config
    lacks is left out, not an AttributeError."""
    from stg_node.avatar import preset

    full = preset("fast")

    class OlderConfig:  # the fast preset as a tree before normal_decide_iter would hold it
        def __init__(self):
            self.__dict__.update({f.name: getattr(full, f.name) for f in dataclasses.fields(full)})
            del self.__dict__["normal_decide_iter"]
            self.changes = {}

        def replace(self, **changes):
            self.changes = changes
            return self

    mid = tradeoff.scaled(OlderConfig(), tradeoff.SCALES["mid"])
    assert mid.changes["iterations"] == round(full.iterations / 3)
    assert mid.changes["nonrigid_decide_iter"] == round(full.nonrigid_decide_iter / 3)
    assert mid.changes["model.max_gaussians"] == round(full.model.max_gaussians / 2)
    assert "normal_decide_iter" not in mid.changes


def test_pareto_front_is_the_set_of_undominated_points():
    rng = np.random.default_rng(3)
    for trial in range(30):
        n = int(rng.integers(1, 25))
        xs = rng.integers(1, 8, n).astype(float).tolist()  # ties on purpose
        ys = rng.integers(1, 8, n).astype(float).tolist()
        if trial % 5 == 0:
            xs[0] = math.nan
        for minimize in (True, False):
            sign = 1 if minimize else -1

            def dominated(i, xs=xs, ys=ys, sign=sign):
                return any(
                    sign * xs[j] <= sign * xs[i] and ys[j] >= ys[i] and (xs[j], ys[j]) != (xs[i], ys[i])
                    for j in range(len(xs))
                    if j != i and math.isfinite(xs[j])
                )

            truth = {i for i in range(n) if math.isfinite(xs[i]) and not dominated(i)}
            front = tradeoff_report.pareto_front(xs, ys, minimize_x=minimize)
            # Exact duplicates of a front point count once.
            assert {(xs[i], ys[i]) for i in front} == {(xs[i], ys[i]) for i in truth}


def test_the_plot_draws_a_point_far_below_the_rest_at_a_floor_three_db_under_the_median():
    """A broken ablation (SH colour under shading, 2026-11-27: 27.7 dB among 32-33 dB rows) squashed
    every other point into a line; below the floor it is drawn at the floor with its value."""
    assert tradeoff_report.plot_floor([33.0, 33.1, 32.2, 27.7]) == pytest.approx(30.0)  # median 33.0
    assert tradeoff_report.plot_floor([33.0, 32.5, 31.0]) is None  # all within 3 dB of the median
    odd = [33.0, math.nan, 29.9, 33.2, 33.1, 32.8]  # NaN left out: median of five, 33.0
    assert tradeoff_report.plot_floor(odd, span_db=3.0) == pytest.approx(30.0)
    assert tradeoff_report.plot_floor([]) is None and tradeoff_report.plot_floor([math.nan]) is None


def test_the_docs_section_is_replaced_between_its_markers_and_nothing_else_changes(tmp_path):
    doc = tmp_path / "BENCH.md"
    doc.write_text("# Benchmarks\n\nintro\n\n## Other\n\nkeep me\n")
    first = f"{tradeoff_report.BEGIN}\nfirst table\n{tradeoff_report.END}\n"
    tradeoff_report.write_section(doc, first)
    text = doc.read_text()
    assert text.startswith("# Benchmarks\n\nintro\n\n## Other\n\nkeep me\n") and "first table" in text
    text = text.replace("keep me", "keep me too") + "\n## After\n\ntail\n"
    doc.write_text(text)
    tradeoff_report.write_section(doc, f"{tradeoff_report.BEGIN}\nsecond table\n{tradeoff_report.END}\n")
    again = doc.read_text()
    assert "second table" in again and "first table" not in again
    assert again.count(tradeoff_report.END) == 1 and "keep me too" in again and again.endswith("tail\n")
    doc.write_text(again.replace(tradeoff_report.END, ""))
    with pytest.raises(ValueError, match="one trade-off marker"):
        tradeoff_report.write_section(doc, first)


def _run_tool(tmp_path: Path, *extra: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, STG_THREADS="1", PYTHONPATH=str(ROOT))
    args = [sys.executable, str(ROOT / "tools" / "tradeoff.py"), "--quick", "--out", str(tmp_path / "out")]
    args += ["--docs", str(tmp_path / "BENCH.md"), "--plot", str(tmp_path / "pareto.png"), "--no-progress"]
    return subprocess.run([*args, *extra], cwd=ROOT, env=env, capture_output=True, text=True, timeout=1800)


def _check_sane(record: dict) -> None:
    name = record["name"]
    assert record["train"]["skipped_steps"] == 0, name
    assert record["it_per_s"] > 0 and record["train"]["train_seconds"] > 0, name
    assert 0 < record["render"]["cpu_ms"] < 10_000 and record["render"]["cpu_ms_no_skip"] > 0, name
    assert record["train"]["gaussians"] > 0 and 0.0 <= record["train"]["active_motion_fraction"] <= 1.0, name
    assert record["train"]["model_mb"] > 0, name
    for split in ("novel_view", "novel_pose"):
        scores = record[split]
        assert 10.0 < scores["psnr"] < 60.0, (name, split, scores)
        assert 0.0 < scores["ssim"] <= 1.0, (name, split)
        assert math.isnan(scores["lpips"]) or 0.0 <= scores["lpips"] < 1.0, (name, split)
        assert scores["views"] > 0
        if scores["fast_pixels"]:
            assert 3.0 < scores["fast_psnr"] < 60.0, (name, split)
        # The garment is seen in every split of every subject (the shirt's front or back).
        assert 0.05 < scores["garment_fraction_of_body"] < 0.8, (name, split)
        assert 3.0 < scores["garment_psnr"] < 60.0, (name, split)
    on = record["train"]["active_on_garment_fraction"]
    assert (math.isnan(on) and record["train"]["active_motion_count"] == 0) or 0.0 <= on <= 1.0, name


def _check_outputs(tmp_path: Path, expect_measured: set[str]) -> dict:
    records = {r["name"]: r for r in json.loads((tmp_path / "out" / "results.json").read_text())}
    measured = {n for n, r in records.items() if r["measured"] and not r["alias"]}
    assert measured == expect_measured
    for name in measured:
        _check_sane(records[name])
    doc = (tmp_path / "BENCH.md").read_text()
    assert doc.count(tradeoff_report.END) == 1 and tradeoff_report.HEADER in doc
    assert "python tools/tradeoff.py --quick" in doc and "Machine:" in doc
    for record in records.values():
        assert f"| {record['label']} |" in doc
    png = (tmp_path / "pareto.png").read_bytes()
    assert png.startswith(b"\x89PNG") and len(png) > 10_000
    return records


def test_quick_run_of_one_configuration_writes_table_and_plot(tmp_path):
    result = _run_tool(tmp_path, "--only", "preset_fast")
    assert result.returncode == 0, result.stderr[-3000:]
    records = _check_outputs(tmp_path, {"preset_fast"})
    assert records["full_fast"]["measured"] and records["full_fast"]["alias"] == "preset_fast"
    assert "not measured in this run" in (tmp_path / "BENCH.md").read_text()
    # The run folder is what stg-train writes: stg-eval scores it the same.
    from stg_node.cli.evaluate import main as stg_eval

    run_dir = tmp_path / "out" / "runs" / "preset_fast"
    assert (
        stg_eval([str(run_dir), "--split", "novel_view", "--json", "--lpips", "none", "--no-progress"]) == 0
    )
    # A result whose renders were timed another way is re-timed on the next run, not trained again.
    stored = tmp_path / "out" / "results" / "preset_fast.json"
    record = json.loads(stored.read_text())
    assert record["render"]["method"] == tradeoff.RENDER_METHOD
    record["render"] = {"cpu_ms": -1.0, "cpu_ms_no_skip": -1.0, "cuda_ms": None, "cuda_ms_no_skip": None}
    stored.write_text(json.dumps(record))
    again = _run_tool(tmp_path, "--only", "preset_fast")
    assert again.returncode == 0, again.stderr[-3000:]
    assert "timing its renders again" in again.stderr and "training" not in again.stderr
    retimed = json.loads(stored.read_text())
    assert retimed["render"]["method"] == tradeoff.RENDER_METHOD and retimed["render"]["cpu_ms"] > 0
    assert retimed["novel_view"] == record["novel_view"]  # the scores are kept


def test_bad_usage_is_refused(tmp_path):
    result = _run_tool(tmp_path, "--only", "warp_drive")
    assert result.returncode == 2 and "warp_drive" in result.stderr
    result = _run_tool(tmp_path, "--scale", "mid", "--list")  # _run_tool passes --quick
    assert result.returncode == 2 and "contradict" in result.stderr


@pytest.mark.slow
def test_quick_grid_end_to_end_and_a_rerun_reuses_results(tmp_path):
    result = _run_tool(tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    expected = {r.name for r in tradeoff.grid("fast") if not r.alias_of}
    records = _check_outputs(tmp_path, expected)
    assert records["lbs_only"]["train"]["active_motion_fraction"] == 0.0
    assert records["sh_color"]["config"]["model"]["color"] == "sh"
    for name in ("lbs_only", "no_flow_densify", "sh_color"):
        assert records[name]["train"]["gaussians"] != records["preset_quality"]["train"]["gaussians"]
    assert records["preset_quality"]["train"]["iterations"] > records["preset_fast"]["train"]["iterations"]
    doc = (tmp_path / "BENCH.md").read_text()
    assert "not measured" not in doc
    # A re-run measures nothing again (results are fingerprinted) and replaces the section in place.
    again = _run_tool(tmp_path)
    assert again.returncode == 0
    assert (tmp_path / "BENCH.md").read_text().count(tradeoff_report.BEGIN) == 1
    assert "preset_fast: reusing the result" in again.stderr and "training" not in again.stderr


def test_a_partial_full_scale_run_does_not_replace_the_docs_table(tmp_path):
    """docs/BENCHMARKS.md's table takes a complete grid only: a partial run's report goes beside its
    runs unless --docs names a file."""
    import argparse

    rows = [row for row in tradeoff.grid("fast") if not row.alias_of]
    docs, plot = Path("docs/BENCHMARKS.md"), Path("docs/tradeoff_pareto.png")
    args = argparse.Namespace(docs=None, plot=None)
    partial = {rows[0].name: {}}
    assert tradeoff.partial_report_targets(rows, partial, args, tmp_path, docs, plot, False) == (
        tmp_path / "BENCHMARKS_partial.md",
        tmp_path / "tradeoff_pareto_partial.png",
    )
    complete = {row.name: {} for row in rows}
    assert tradeoff.partial_report_targets(rows, complete, args, tmp_path, docs, plot, False) == (docs, plot)
    chosen = argparse.Namespace(docs=str(docs), plot=str(plot))
    assert tradeoff.partial_report_targets(rows, partial, chosen, tmp_path, docs, plot, False) == (docs, plot)
    assert tradeoff.partial_report_targets(rows, partial, args, tmp_path, docs, plot, True) == (docs, plot)
