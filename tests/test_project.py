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


def _import_graph() -> dict[str, set[str]]:
    """stg_node's modules -> the stg_node modules they import (at the top or inside functions)."""
    import ast

    package = ROOT / "stg_node"
    modules = {}
    for path in package.rglob("*.py"):
        parts = path.relative_to(ROOT).with_suffix("").parts
        modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    graph = {}
    for name, path in modules.items():
        deps = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                for alias in node.names:
                    child = f"{node.module}.{alias.name}"
                    deps.add(child if child in modules else node.module)
            elif isinstance(node, ast.Import):
                deps.update(alias.name for alias in node.names)
        graph[name] = {d for d in deps if d in modules and d != name}
    return graph


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle of ``graph`` (depth-first search), or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for dep in sorted(graph[node]):
            if state.get(dep) == 1:
                return path[path.index(dep) :] + [dep]
            if dep not in state and (found := visit(dep)):
                return found
        path.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return None


def test_the_package_has_no_import_cycles():
    """Not even through imports inside functions (checkpoint.py and trainer.py once imported each other)."""
    assert _cycle(_import_graph()) is None, " -> ".join(_cycle(_import_graph()))
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]  # the search finds one
    assert "stg_node.avatar.checkpoint" in _import_graph()["stg_node.avatar.trainer"]


def _project_text_files():
    """Tracked source, docs, launch and config files (what a user's clone holds)."""
    import subprocess

    listed = subprocess.run(
        ["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.split()
    suffixes = {".py", ".md", ".yaml", ".yml", ".toml", ".sh", ".cfg", ".txt", ".json"}
    for name in listed:
        path = ROOT / name
        if path.suffix in suffixes and path.is_file() and path.stat().st_size < 2_000_000:
            yield path


def test_the_project_stands_alone():
    """Nothing refers to files outside the clone (a sibling shared/ folder, a machine's /work)."""
    # Spelt in pieces so that this line does not match itself.
    outside = re.compile(r"\.\./" + "shared" + r"\b|(?<![\w.])/" + "work/")
    offenders = [
        f"{path.relative_to(ROOT)}:{number}"
        for path in _project_text_files()
        for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1)
        if outside.search(line)
    ]
    assert not offenders, f"references outside the project: {offenders}"


def test_readme_links_the_architecture_page():
    readme = (ROOT / "README.md").read_text()
    assert "(docs/ARCHITECTURE.md)" in readme
    assert (ROOT / "docs" / "ARCHITECTURE.md").is_file()
