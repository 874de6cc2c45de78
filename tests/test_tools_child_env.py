"""tools/baseline.child_env: a measuring child imports the chosen tree first and keeps the
caller's PYTHONPATH (a GPU machine's gsplat lived there and the children lost it)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

from baseline import child_env  # noqa: E402


def test_the_tree_comes_first_and_the_callers_entries_stay(monkeypatch, tmp_path):
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(["/opt/a", "/opt/b"]))
    env = child_env(tmp_path, STG_THREADS="1")
    assert env["PYTHONPATH"].split(os.pathsep) == [str(tmp_path), "/opt/a", "/opt/b"]
    assert env["STG_THREADS"] == "1"
    monkeypatch.delenv("PYTHONPATH")
    assert child_env(tmp_path)["PYTHONPATH"] == str(tmp_path)


def test_a_child_imports_the_tree_and_a_package_only_on_the_callers_path(monkeypatch, tmp_path):
    extra = tmp_path / "site"
    extra.mkdir()
    (extra / "only_on_callers_path.py").write_text("WHERE = 'caller'\n")
    monkeypatch.setenv("PYTHONPATH", str(extra))
    code = "import only_on_callers_path, stg_node; print(only_on_callers_path.WHERE, stg_node.__file__)"
    done = subprocess.run(
        [sys.executable, "-c", code], env=child_env(ROOT), cwd=tmp_path, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    where, package = done.stdout.split()
    assert where == "caller"
    assert Path(package).resolve().is_relative_to(ROOT)
