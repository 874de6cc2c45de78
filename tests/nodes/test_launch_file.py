"""Launch files: arguments, substitutions, includes, checks, and errors that name the file and line."""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import pytest
import yaml

from stg_node.cli.launch import main as launch_main
from stg_node.launch import LaunchFileError, read_launch
from stg_node.launch.schema import launch_schema, schema_text

ROOT = Path(__file__).resolve().parents[2]
ECHO = "tests.nodes.sample_nodes:Echo"


def write(folder: Path, name: str, text: str) -> Path:
    path = folder / name
    path.write_text(textwrap.dedent(text).lstrip("\n"))
    return path


def error_of(path: Path, **overrides) -> LaunchFileError:
    with pytest.raises(LaunchFileError) as info:
        read_launch(path, overrides)
    return info.value


def test_arguments_defaults_overrides_and_substitutions(tmp_path, monkeypatch):
    monkeypatch.setenv("STG_TEST_VAR", "from-env")
    (tmp_path / "exists").mkdir()
    path = write(
        tmp_path,
        "a.yaml",
        f"""
        args:
          bus: {{default: "ipc://{tmp_path}/bus", doc: the bus}}
          out: runs/x
          limit: 3
        env: {{A: $(env STG_TEST_VAR), B: $(env STG_UNSET_VAR fallback)}}
        bus: {{url: $(arg bus)}}
        nodes:
          - name: echo
            kind: {ECHO}
            params: {{exit_after_s: $(arg limit), flush_file: $(arg out)/f}}
          - name: skipped
            cmd: [sleep, "1"]
            if: $(exists $(dirname)/missing)
          - name: kept
            cmd: [echo, $(dirname)]
            unless: $(exists $(dirname)/missing)
            after: [echo, skipped]
        """,
    )
    spec = read_launch(path, {"limit": "2.5"})
    echo = spec.node("echo")
    assert echo.params.exit_after_s == 2.5 and echo.params.flush_file == "runs/x/f"
    assert echo.env == {"A": "from-env", "B": "fallback"}
    assert spec.skipped == ["skipped"] and spec.node("kept").entry.cmd == ["echo", str(tmp_path)]
    assert spec.bus.url == f"ipc://{tmp_path}/bus"
    assert echo.ready == "heartbeat" and spec.node("kept").ready == "started"
    cmd = echo.command(spec.bus)
    assert cmd[1:4] == ["-m", "stg_node.nodes", ECHO]
    assert json.loads(cmd[cmd.index("--params") + 1])["exit_after_s"] == 2.5


def test_includes_pass_arguments_down_and_prefix_names_and_namespaces(tmp_path):
    write(
        tmp_path,
        "inner.yaml",
        f"""
        args: {{bus: "", rate: 1, who: inner}}
        env: {{INNER: "1"}}
        nodes:
          - {{name: echo, kind: {ECHO}, params: {{setup_s: $(arg rate)}}, namespace: cam}}
          - {{name: tail, cmd: [echo, $(arg who)], after: [echo]}}
        """,
    )
    path = write(
        tmp_path,
        "outer.yaml",
        """
        args: {bus: "ipc:///tmp/stg-test-bus", rate: 7}
        bus: {url: $(arg bus), namespace: site}
        include:
          - {file: inner.yaml, namespace: rig1, args: {who: outer}}
        nodes:
          - {name: last, cmd: ["true"], after: [rig1/tail]}
        """,
    )
    spec = read_launch(path)
    echo = spec.node("rig1/echo")
    assert echo.params.setup_s == 7.0  # the includer's argument of the same name
    assert echo.namespace == "site/rig1/cam" and echo.env == {"INNER": "1"}
    assert spec.node("rig1/tail").entry.cmd == ["echo", "outer"]
    assert spec.node("rig1/tail").after == ["rig1/echo"]
    assert "--namespace" in echo.command(spec.bus)


@pytest.mark.parametrize(
    ("text", "line", "words"),
    [
        ("nodes:\n  - name: a\n    cmd: [true\n", 4, "not valid YAML"),
        (
            "nodes:\n  - name: a\n    cmd: [x]\n    respwan: true\n",
            4,
            "respwan: unknown parameter; did you mean 'respawn'",
        ),
        (
            f"nodes:\n  - name: a\n    kind: {ECHO}\n    params:\n      setup_s: soon\n",
            5,
            "param 'setup_s': must be a number",
        ),
        (
            f"nodes:\n  - name: a\n    kind: {ECHO}\n    params: {{colour: red}}\n",
            4,
            "'colour': unknown parameter",
        ),
        ("nodes:\n  - {name: a, cmd: [x], if_: true}\n", 2, "write 'if:', not 'if_:'"),
        ("nodes:\n  - name: a\n    kind: nope\n", 3, "unknown node kind 'nope'"),
        ("nodes:\n  - name: a\n    cmd: [x]\n    name: b\n", 4, "key 'name' appears twice"),
        ("nodes:\n  - {name: a, cmd: [x]}\n  - {name: a, cmd: [y]}\n", 3, "a node named 'a' already exists"),
        ("nodes:\n  - {name: a, cmd: [x], kind: y}\n", 2, "exactly one of kind, module or cmd"),
        ("nodes:\n  - {name: a, cmd: [x], after: [b]}\n", 2, "after names no node 'b'"),
        ("nodes:\n  - {name: a, cmd: [x], after: [b]}\n  - {name: b, cmd: [x], after: [a]}\n", 2, "cycle"),
        ("nodes:\n  - {name: a, cmd: [x], ready: soon}\n", 2, "ready 'soon' is not one of"),
        ("nodes:\n  - {name: a, cmd: [x], ready: heartbeat}\n", 2, "only kind nodes send heartbeats"),
        ("nodes:\n  - {name: a, cmd: [$(arg nope)]}\n", 2, "$(arg nope): no such launch argument"),
        ("nodes:\n  - {name: a, cmd: [$(env STG_SURELY_UNSET_X)]}\n", 2, "is not set"),
        ("nodes:\n  - {name: a, cmd: [$(what x)]}\n", 2, "unknown substitution"),
        ("args: {need: {doc: a folder}}\nnodes: []\n", 1, "'need' is required: pass need:=VALUE (a folder)"),
        ("bus: {lanes: {camera/frame: fast}}\n", 1, "lane 'fast'"),
        ("bus: {url: http://x}\n", 1, "bus URL"),
        ("include:\n  - {file: missing.yaml}\n", 2, "does not exist"),
        ("nodes: 3\n", 1, "nodes: must be a list"),
        ("frobnicate: 1\n", 1, "frobnicate: unknown parameter"),
        ("nodes:\n  - {name: a, cmd: [true]}\n", 2, "cmd[0]: must be text, got True (quote it: 'true')"),
    ],
)
def test_a_bad_launch_file_names_file_and_line(tmp_path, text, line, words):
    path = write(tmp_path, "bad.yaml", text)
    err = error_of(path)
    assert err.path == path.resolve() and err.line == line, str(err)
    assert words in str(err)
    assert str(err).startswith(f"{path.resolve()}:{line}: ")


def test_include_errors_point_into_the_included_file_and_cycles_are_refused(tmp_path):
    write(tmp_path, "inner.yaml", "nodes:\n  - {name: x, cmd: [a], respawn: often}\n")
    outer = write(tmp_path, "outer.yaml", "include:\n  - {file: inner.yaml}\n")
    err = error_of(outer)
    assert err.path.name == "inner.yaml" and err.line == 2 and "respawn: must be true or false" in str(err)
    write(tmp_path, "loop_a.yaml", "include: [{file: loop_b.yaml}]\n")
    write(tmp_path, "loop_b.yaml", "include: [{file: loop_a.yaml}]\n")
    assert "include cycle" in str(error_of(tmp_path / "loop_a.yaml"))
    bad_arg = write(tmp_path, "bad_arg.yaml", "include:\n  - file: inner.yaml\n    args: {nope: 1}\n")
    err = error_of(bad_arg)
    assert err.path.name == "bad_arg.yaml" and err.line == 3 and "has no argument 'nope'" in str(err)


def test_unknown_command_line_argument_is_refused(tmp_path):
    path = write(tmp_path, "a.yaml", "args: {out: x}\n")
    assert "unknown launch argument 'ouput' (declared: out)" in str(error_of(path, ouput="y"))


def test_cli_validate_show_args_and_exit_codes(tmp_path, capsys):
    good = write(tmp_path, "good.yaml", f"args: {{n: 1, bus: ''}}\nnodes:\n  - {{name: e, kind: {ECHO}}}\n")
    assert launch_main(["--validate", str(good), "n:=2"]) == 0
    assert "ok (1 node(s)" in capsys.readouterr().out
    assert launch_main(["--show-args", str(good), "n:=5"]) == 0
    assert "n:=5" in capsys.readouterr().out
    assert launch_main(["--validate", str(good), "bad-override"]) == 2
    assert "must look like name:=value" in capsys.readouterr().err
    bad = write(tmp_path, "bad.yaml", "nodes:\n  - {name: e, kind: nope}\n")
    assert launch_main(["--validate", str(bad)]) == 2
    assert f"{bad.resolve()}:2:" in capsys.readouterr().err
    assert launch_main([]) == 2


def test_the_published_schema_is_the_generated_one():
    assert (ROOT / "docs" / "launch.schema.json").read_text() == schema_text()


def test_the_schema_agrees_with_the_parser_on_the_shipped_launch_files():
    """An independent validator (jsonschema) accepts every launch file the parser accepts."""
    jsonschema = pytest.importorskip("jsonschema")
    validator = jsonschema.Draft202012Validator(launch_schema())
    files = sorted((ROOT / "launch").glob("*.yaml"))
    assert files
    for path in files:
        errors = list(validator.iter_errors(yaml.safe_load(path.read_text())))
        assert not errors, f"{path.name}: {errors[0].message}"
    bad = {"nodes": [{"name": "a", "kind": "ingest", "params": {"rate_hz": "fast"}, "respwan": True}]}
    assert len(list(validator.iter_errors(bad))) >= 2


def test_the_launch_guide_documents_every_node_key():
    import dataclasses

    from stg_node.launch.spec import NodeEntry

    guide = (ROOT / "docs" / "LAUNCH.md").read_text()
    for f in dataclasses.fields(NodeEntry):
        name = "if" if f.name == "if_" else f.name
        assert f"`{name}`" in guide, name


def test_nonzero_starts_a_node_only_for_a_number_other_than_zero(tmp_path):
    path = write(
        tmp_path,
        "n.yaml",
        f"""
        args: {{port: 0, bus: "ipc://{tmp_path}/bus"}}
        bus: {{url: $(arg bus)}}
        nodes:
          - name: echo
            kind: {ECHO}
            if: $(nonzero $(arg port))
        """,
    )
    assert read_launch(path).skipped == ["echo"]
    assert read_launch(path, {"port": "0.0"}).skipped == ["echo"]
    assert read_launch(path, {"port": ""}).skipped == ["echo"]
    assert read_launch(path, {"port": "8080"}).node("echo")
    assert "not a number" in str(error_of(path, port="http"))


@pytest.mark.parametrize("name", ["demo", "replay_zju", "live_v4l2", "live_oak", "regression"])
def test_every_shipped_launch_file_takes_foxglove_web_and_host(name, tmp_path):
    required = {
        "replay_zju": {"data_root": str(tmp_path)},
        "regression": {"session": "s", "out": "o", "iters": "1"},
    }
    base = required.get(name, {})
    off = read_launch(ROOT / "launch" / f"{name}.yaml", base)
    assert {"foxglove", "web"} <= set(off.skipped)
    on = read_launch(
        ROOT / "launch" / f"{name}.yaml", {**base, "foxglove": "8765", "web": "8080", "host": "0.0.0.0"}
    )
    assert (on.node("foxglove").params.port, on.node("web").params.port) == (8765, 8080)
    assert on.node("foxglove").params.host == on.node("web").params.host == "0.0.0.0"
