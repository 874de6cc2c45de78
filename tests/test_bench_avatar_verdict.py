"""tools/bench_avatar.quality_verdict: the "same result" check of issue 24 is one-sided. A faster
step that loses more than 0.1 dB misses; one that scores higher is reported, not failed."""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

from bench_avatar import quality_verdict  # noqa: E402


def test_a_loss_beyond_the_tolerance_on_either_split_misses():
    assert quality_verdict(-0.11, 0.0) == "MISSED"
    assert quality_verdict(0.3, -0.2) == "MISSED"


def test_within_the_tolerance_is_the_same_result():
    assert quality_verdict(-0.09, 0.05) == "OK"
    assert quality_verdict(0.1, -0.1) == "OK"


def test_a_gain_beyond_the_tolerance_is_reported_as_better():
    assert quality_verdict(0.26, 0.2) == "OK, better"
