"""tools/bench_avatar's children report their phases while they run: a GPU session cut by its time
limit must still show where a child's time went (docs/BENCHMARKS.md, "Third GPU session")."""

from __future__ import annotations

import io
import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

from bench_avatar import run_child  # noqa: E402

# a child as bench_avatar's workers are: the module's _phase on stderr, its result on stdout
CHILD = """
import json, os, sys, time
sys.path.insert(0, {tools!r})
import bench_avatar
bench_avatar._phase("imports")
print("a warning the parent keeps for errors", file=sys.stderr, flush=True)
deadline = time.monotonic() + 60
while not os.path.exists({seen!r}):  # the parent has shown the phase before this child is done
    if time.monotonic() > deadline:
        sys.exit("the parent never showed the first phase while this child ran")
    time.sleep(0.01)
bench_avatar._phase("model of 3 Gaussians")
print(json.dumps({{"wall_ms": 1.5}}))
sys.exit({code})
"""


class SeenFile(io.StringIO):
    """The progress stream: creates ``path`` once a line has been written (what the child waits for)."""

    def __init__(self, path: Path):
        super().__init__()
        self.path = path

    def write(self, text: str) -> int:
        n = super().write(text)
        if "imports" in text:
            self.path.touch()
        return n


def _child(tmp_path: Path, code: int = 0) -> list[str]:
    script = CHILD.format(tools=str(ROOT / "tools"), seen=str(tmp_path / "seen"), code=code)
    return [sys.executable, "-c", script]


def test_phases_are_shown_while_the_child_runs_and_the_result_comes_back(tmp_path):
    progress = SeenFile(tmp_path / "seen")
    result = run_child(_child(tmp_path), dict(os.environ), "render 50000 exact new", "child", progress)
    assert result == {"wall_ms": 1.5}
    lines = progress.getvalue().splitlines()
    assert [line.split(": ", 1)[1] for line in lines[:2]] == ["imports", "model of 3 Gaussians"]
    assert all(line.startswith("  [render 50000 exact new]") for line in lines)
    assert lines[-1].split("] ", 1)[1].startswith("done after")
    seconds = [float(line.split("]", 1)[1].split(" s:")[0]) for line in lines[:2]]
    assert 0.0 <= seconds[0] <= seconds[1]
    assert "warning" not in progress.getvalue()  # other stderr is not progress


def test_a_failing_child_names_itself_and_keeps_its_other_output(tmp_path):
    progress = SeenFile(tmp_path / "seen")
    with pytest.raises(SystemExit) as failed:
        run_child(_child(tmp_path, code=3), dict(os.environ), "step 20000 new", "the step child", progress)
    message = str(failed.value)
    assert "the step child failed (exit 3)" in message
    assert "a warning the parent keeps for errors" in message
    assert "bench-phase" not in message
    assert "done after" not in progress.getvalue()


# a child that would go on measuring for a minute, then say it finished
LONG_CHILD = """
import os, sys, time
sys.path.insert(0, {tools!r})
import bench_avatar
bench_avatar._phase("imports")
deadline = time.monotonic() + 60
while time.monotonic() < deadline:
    time.sleep(0.05)
open({finished!r}, "w").close()
"""


class Interrupting(io.StringIO):
    """The parent interrupted (Ctrl-C, or a time limit's SIGTERM, which the bench turns into one)
    while it shows a child's first phase."""

    def write(self, text: str) -> int:
        raise KeyboardInterrupt


def test_an_interrupted_parent_stops_its_child(tmp_path):
    finished = tmp_path / "finished"
    cmd = [sys.executable, "-c", LONG_CHILD.format(tools=str(ROOT / "tools"), finished=str(finished))]
    with pytest.raises(KeyboardInterrupt):
        run_child(cmd, dict(os.environ), "render 50000 exact new", "child", Interrupting())
    # run_child returns once the child is gone: killed, it never got to finish
    assert not finished.exists()
