"""The regression run (tools/regression.py, docs/RECORDING.md "Regression tests"): a synthetic session
replayed in lockstep through the real trainer and renderer nodes reproduces the committed golden
renders; the comparison itself fails changed renders by its stated tolerance (checked against the
closed form of PSNR for a constant offset) and passes the golden against itself; bless writes what
compare accepts."""

from __future__ import annotations

import importlib.util
import io
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from stg_node.cli.runner import CommandFailed

ROOT = Path(__file__).resolve().parents[1]


def _load_tool():
    spec = importlib.util.spec_from_file_location("stg_regression_tool", ROOT / "tools" / "regression.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the file executes
    spec.loader.exec_module(module)
    return module


regression = _load_tool()
FAST = regression.VARIANTS["fast"]


def golden_views(name: str = "fast"):
    meta, images = regression.load_golden(regression.GOLDEN_ROOT / name)
    views = [
        regression.EvalView(**{k: v[k] for k in ("request_id", "split", "camera", "frame", "time")})
        for v in meta["views"]
    ]
    return meta, images, views


def _report(outcome) -> str:
    out = io.StringIO()
    regression.report(outcome, out)
    return out.getvalue()


def _check_session(path: Path, variant) -> None:
    """The session as the tool means it, read by the mcap package alone: frames, each followed by
    its pose, then one view request per evaluation view."""
    with open(path, "rb") as f:
        rows = [(c.topic, m) for _s, c, m in make_reader(f).iter_messages()]
    topics = [t for t, _m in rows]
    n = variant.train_frames
    assert topics[: 2 * n] == ["camera/frame", "body/pose"] * n
    assert set(topics[2 * n :]) == {"avatar/view"}
    assert [m.sequence for t, m in rows if t == "camera/frame"] == list(range(n))


def test_the_fast_variant_reproduces_the_golden(tmp_path):
    outcome = regression.run_variant(FAST, tmp_path, progress=False)
    text = _report(outcome)
    assert outcome.comparison.passed, text + f"\n(work folder kept: {tmp_path})"
    assert len(outcome.comparison.results) == 7 and outcome.comparison.missing == []
    _check_session(tmp_path / "session.mcap", FAST)


@pytest.mark.slow
def test_the_full_variant_reproduces_the_golden(tmp_path):
    """360 iterations: also densification and the flow rounds of the fast preset."""
    full = regression.VARIANTS["full"]
    outcome = regression.run_variant(full, tmp_path, progress=False)
    assert outcome.comparison.passed, _report(outcome) + f"\n(work folder kept: {tmp_path})"


def test_the_comparison_passes_the_golden_itself_and_fails_changed_renders(tmp_path):
    meta, golden, views = golden_views()
    folder = regression.GOLDEN_ROOT / "fast"
    same = regression.compare(FAST, golden, folder, views)
    assert same.passed and all(math.isinf(r.psnr_db) and r.mean_abs == 0 for r in same.results)

    def offset(render, c):  # +c on every covered pixel: PSNR over them is 20 log10(255 / c) exactly
        image = render.image.astype(np.int16)
        covered = render.alpha > 0
        assert image[covered].max() <= 255 - c  # no clipping, so the closed form holds
        image[covered] += c
        return regression.Render(image.astype(np.uint8), render.alpha)

    for c, passes in ((2, True), (3, False)):
        changed = {i: offset(r, c) for i, r in golden.items()}
        result = regression.compare(FAST, changed, folder, views)
        assert result.passed is passes
        for r in result.results:
            assert r.psnr_db == pytest.approx(20 * math.log10(255 / c), abs=1e-6)
    assert 20 * math.log10(255 / 3) < regression.TOLERANCE_DB["fast"] < 20 * math.log10(255 / 2)
    assert set(regression.TOLERANCE_DB) == set(regression.VARIANTS)

    shifted = {
        i: regression.Render(np.roll(r.image, 1, axis=1), np.roll(r.alpha, 1, axis=1))
        for i, r in golden.items()
    }
    assert not regression.compare(FAST, shifted, folder, views).passed  # the avatar moved one pixel
    fewer = {i: r for i, r in golden.items() if i != 3}
    result = regression.compare(FAST, fewer, folder, views)
    assert not result.passed and result.missing == [3]


def test_bless_writes_what_compare_accepts_and_a_changed_variant_asks_for_a_new_bless(tmp_path):
    meta, golden, views = golden_views()
    regression.bless(FAST, golden, views, tmp_path / "fast", {"iterations": 48})
    assert regression.compare(FAST, golden, tmp_path / "fast", views).passed
    with pytest.raises(CommandFailed, match="re-bless"):
        regression.compare(replace(FAST, steps_per_frame=7), golden, tmp_path / "fast", views)
    with pytest.raises(CommandFailed, match="not blessing"):
        regression.bless(FAST, {}, views, tmp_path / "empty", {})


def test_goldens_are_small_and_complete():
    total = 0
    for name in regression.VARIANTS:
        meta, images, views = golden_views(name)
        assert meta["variant"]["name"] == name and len(images) == len(views) > 0
        total += sum(f.stat().st_size for f in (regression.GOLDEN_ROOT / name).iterdir())
    assert total < 300_000


def test_the_command_line_reports_a_missing_golden_as_bad_usage(tmp_path, capsys):
    assert regression.main(["--golden", str(tmp_path / "none")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_the_command_line_exits_1_on_a_regression_and_says_how_to_rebless(tmp_path, monkeypatch, capsys):
    meta, golden, views = golden_views()
    shifted = {i: regression.Render(np.roll(r.image, 2, axis=0), r.alpha) for i, r in golden.items()}
    failing = regression.compare(FAST, shifted, regression.GOLDEN_ROOT / "fast", views)

    def fake_run(variant, work, **options):  # the comparison of a run whose renders moved
        return regression.Outcome(variant.name, False, failing, work, regression.GOLDEN_ROOT / "fast")

    monkeypatch.setattr(regression, "run_variant", fake_run)
    assert regression.main(["--variant", "fast"]) == 1
    captured = capsys.readouterr()
    assert "fast: FAIL (tolerance: PSNR >= 40 dB)" in captured.out
    assert "re-bless with --bless" in captured.err
