"""tools/test_repeat.py: N runs of a suite, per-test failure counts, busy-loop and background runs."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# A suite with a steady test, one that fails on every second run (a counter file keeps the runs
# apart), and one that reports how it was started (SIGINT ignored: a background job).
SUITE = """
import os, signal
from pathlib import Path

COUNTER = Path(os.environ["REPEAT_COUNTER"])

def test_steady():
    assert True

def test_every_second_run_fails():
    n = int(COUNTER.read_text()) + 1 if COUNTER.exists() else 1
    COUNTER.write_text(str(n))
    assert n % 2 == 1, f"run {n} failed on purpose"

def test_how_it_was_started():
    started = "background" if signal.getsignal(signal.SIGINT) is signal.SIG_IGN else "foreground"
    Path(os.environ["REPEAT_COUNTER"] + "." + started).touch()
"""


def test_runs_are_counted_per_test_and_background_runs_start_as_a_shell_would(tmp_path):
    suite = tmp_path / "test_suite.py"
    suite.write_text(SUITE)
    counter = tmp_path / "count"
    result = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "test_repeat.py"), "3", "--busy-runs", "1",
         "--background-runs", "1", "--work", str(tmp_path / "work"), "--json", str(tmp_path / "r.json"),
         "--", str(suite), "--rootdir", str(tmp_path)],
        cwd=tmp_path, capture_output=True, text=True, timeout=300,
        env={**os.environ, "REPEAT_COUNTER": str(counter)},
    )  # fmt: skip
    assert result.returncode == 1, result.stdout + result.stderr  # a run failed
    assert "1/3" in result.stdout and "test_every_second_run_fails: " in result.stdout
    assert "run 2 failed on purpose" in result.stdout
    report = json.loads((tmp_path / "r.json").read_text())
    assert [r["busy"] for r in report["runs"]] == [True, False, False]
    assert [r["background"] for r in report["runs"]] == [False, False, True]
    assert [len(r["failed"]) for r in report["runs"]] == [0, 1, 0]
    assert all(r["tests"] == 3 for r in report["runs"])
    assert report["failures"] == {"test_suite::test_every_second_run_fails": 1}
    assert (tmp_path / "count.background").exists() and (tmp_path / "count.foreground").exists()
