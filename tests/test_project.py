"""The project's own promises: CI runs the README's test command; console scripts are real."""

import importlib
import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _readme_command(marker: str) -> str:
    readme = (ROOT / "README.md").read_text()
    match = re.search(rf"<!-- {marker} -->\s*```(?:sh|bash)?\n(.+?)\n```", readme, re.S)
    assert match, f"README.md must mark a command with <!-- {marker} -->"
    return match.group(1).strip()


def test_readme_main_command_is_a_make_target():
    command = _readme_command("main-command")
    assert command.startswith("make ")
    target = command.split()[1]
    assert re.search(rf"^{target}:", (ROOT / "Makefile").read_text(), re.M), (
        f"Makefile has no {target} target"
    )


def test_ci_runs_the_readme_test_command():
    command = _readme_command("test-command")
    ci_lines = [line.strip() for line in (ROOT / ".ci" / "run").read_text().splitlines()]
    assert command in ci_lines


def test_console_scripts_resolve_to_callables():
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"].get("scripts", {})
    for name, target in scripts.items():
        module_name, _, attr = target.partition(":")
        module = importlib.import_module(module_name)
        assert callable(getattr(module, attr)), f"console script {name} -> {target} is not callable"


def test_markers_are_declared():
    ini = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]
    declared = {m.split(":")[0] for m in ini["markers"]}
    assert {"slow", "gpu"} <= declared
    assert "not slow" in ini["addopts"]
