"""Typed node parameters: coercion from launch-file text, and errors that name the parameter."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import pytest

from stg_node.nodes import NODE_KINDS, load_node_class
from stg_node.nodes.params import ParamError, describe_params, param, params_json_schema, parse_params

ROOT = Path(__file__).resolve().parents[2]


@dataclass
class P:
    path: str = param(doc="a folder")
    rate_hz: float = param(30.0, min=0.0, unit="Hz")
    count: int = param(3, min=1, max=10)
    loop: bool = param(False)
    mode: Literal["a", "b"] = param("a")
    sizes: list[int] = param([1, 2])
    limit: float | None = param(None)
    options: dict[str, float] = param({})

    def validate(self):
        if self.mode == "b" and not self.loop:
            raise ValueError("mode b needs loop")


def test_strings_from_substitutions_become_the_declared_types():
    p = parse_params(
        P,
        {
            "path": "x",
            "rate_hz": "1e3",
            "count": "7",
            "loop": "yes",
            "mode": "b",
            "sizes": "[4, 5]",
            "limit": "none",
        },
    )
    assert (p.rate_hz, p.count, p.loop, p.mode, p.sizes, p.limit) == (1000.0, 7, True, "b", [4, 5], None)
    assert parse_params(P, {"path": 5, "sizes": "6, 7", "limit": "2.5", "options": "{a: 1}"}).sizes == [6, 7]
    assert parse_params(P, {"path": "x", "count": 4.0}).count == 4


def test_defaults_are_fresh_per_instance():
    a, b = parse_params(P, {"path": "x"}), parse_params(P, {"path": "y"})
    a.sizes.append(9)
    assert b.sizes == [1, 2]


@pytest.mark.parametrize(
    ("values", "name", "words"),
    [
        ({}, "path", "required"),
        ({"path": "x", "rate": 3}, "rate", "did you mean 'rate_hz'"),
        ({"path": "x", "count": "many"}, "count", "must be an integer"),
        ({"path": "x", "count": True}, "count", "must be an integer"),
        ({"path": "x", "count": 2.5}, "count", "must be an integer"),
        ({"path": "x", "count": 11}, "count", "<= 10"),
        ({"path": "x", "rate_hz": -1}, "rate_hz", ">= 0.0"),
        ({"path": "x", "rate_hz": "nan"}, "rate_hz", "a number"),
        ({"path": "x", "loop": "maybe"}, "loop", "true or false"),
        ({"path": "x", "mode": "c"}, "mode", "one of 'a', 'b'"),
        ({"path": "x", "sizes": [1, "z"]}, "sizes[1]", "an integer"),
        ({"path": ["x"]}, "path", "text"),
    ],
)
def test_bad_values_name_the_parameter(values, name, words):
    with pytest.raises(ParamError) as info:
        parse_params(P, values, where="node 'n'")
    assert info.value.name == name
    assert words in str(info.value) and "node 'n'" in str(info.value)


def test_validate_runs_after_the_fields():
    with pytest.raises(ParamError, match="mode b needs loop"):
        parse_params(P, {"path": "x", "mode": "b"})


def test_description_and_schema_agree_with_the_class():
    info = {i.name: i for i in describe_params(P)}
    assert info["path"].required and not info["rate_hz"].required and info["rate_hz"].unit == "Hz"
    schema = params_json_schema(P)
    assert schema["required"] == ["path"] and schema["additionalProperties"] is False
    assert schema["properties"]["count"]["anyOf"][0] == {"type": "integer", "minimum": 1, "maximum": 10}


@pytest.mark.parametrize("kind", sorted(NODE_KINDS))
def test_every_node_kind_documents_its_params(kind):
    cls = load_node_class(kind)
    for info in describe_params(cls.Params):
        assert info.doc, f"{kind}.{info.name} has no doc"


def test_loading_node_kinds_and_launch_files_imports_no_heavy_package():
    """stg-launch --validate and --list stay fast: torch, OpenCV, depthai load only when a node starts."""
    code = (
        "import sys\n"
        "from stg_node.nodes import NODE_KINDS, load_node_class\n"
        "import stg_node.launch.schema, stg_node.cli.launch\n"
        "[load_node_class(k) for k in NODE_KINDS]\n"
        "print(sorted(m for m in ('torch', 'cv2', 'depthai', 'PIL') if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


@pytest.mark.parametrize("kind", sorted(NODE_KINDS))
def test_docs_show_each_kinds_parameters_as_the_code_declares_them(kind):
    from stg_node.nodes.params import params_markdown

    assert params_markdown(load_node_class(kind).Params) in (ROOT / "docs" / "NODES.md").read_text()
