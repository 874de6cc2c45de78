"""The message classes rendered in proto/'s YAML structure, and a comparison with proto/ files.

proto/*.yaml is the hand-written, language-neutral reference; :func:`differences` reports
every way a class disagrees with its file (type, version, topic, lane, latching, limits,
fields with their types, defaults, bounds and units, arrays with dtypes, shapes, units).
Descriptions are prose and are not compared, only required to be present.
tests/test_bus_proto.py runs it for every message type.
"""

from __future__ import annotations

import math
from pathlib import Path

import yaml

from stg_node.bus.messages import REGISTRY, Message
from stg_node.bus.spec import ArraySpec, ScalarSpec
from stg_node.safe_load import load_yaml


def _scalar(s: ScalarSpec) -> dict:
    out: dict = {"type": s.kind, "required": s.required}
    if not s.required:
        out["default"] = s.default
    if s.min is not None:
        out["min"] = s.min
    if s.max is not None:
        out["max"] = s.max
    if s.choices is not None:
        out["choices"] = list(s.choices)
    if s.kind in ("float", "map[str,float]"):
        out["finite"] = s.finite
    if s.unit:
        out["unit"] = s.unit
    out["description"] = s.doc
    return out


def _array(a: ArraySpec) -> dict:
    out: dict = {"dtype": a.dtype, "shape": list(a.shape), "required": a.required}
    if a.dtype.startswith("float"):
        out["finite"] = a.finite
    if a.unit:
        out["unit"] = a.unit
    out["description"] = a.doc
    return out


def schema_of(cls: type[Message]) -> dict:
    """``cls``'s spec as the dict its proto/ YAML file should load to."""
    spec = cls.SPEC
    out: dict = {
        "type": spec.type,
        "version": spec.version,
        "topic": spec.topic,
        "lane": spec.lane,
        "latched": spec.latched,
        "description": spec.doc,
        "limits": {
            "max_bytes": spec.max_bytes,
            "dims": {k: {"min": d.min, "max": d.max, "description": d.doc} for k, d in spec.dims.items()},
        },
        "fields": {s.name: _scalar(s) for s in spec.scalars},
        "arrays": {a.name: _array(a) for a in spec.arrays},
    }
    if spec.array_set is not None:
        aset = spec.array_set
        out["array_set"] = {
            "field": aset.name,
            "dtypes": list(aset.dtypes),
            "max_count": aset.max_count,
            "max_ndim": aset.max_ndim,
            "max_dim": aset.max_dim,
            "name_pattern": aset.name_pattern,
            "finite": aset.finite,
            "description": aset.doc,
        }
    return out


def load_proto(directory: str | Path) -> dict[str, dict]:
    """Every message schema in ``directory`` (not envelope.yaml), by type name."""
    out = {}
    for path in sorted(Path(directory).glob("*.yaml")):
        if path.name == "envelope.yaml":
            continue
        data = load_yaml(path)
        out[data["type"]] = {**data, "_file": path.name}
    return out


def _same(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    if isinstance(a, bool) or isinstance(b, bool):
        return a is b
    return a == b


def _compare(where: str, want: dict, got: dict, problems: list[str]) -> None:
    """Compare two schema dicts; 'description' values must merely be non-empty in ``got``."""
    for key in sorted(set(want) | set(got)):
        if key == "_file":
            continue
        if key not in got:
            problems.append(f"{where}: {key!r} is missing from proto")
        elif key not in want:
            problems.append(f"{where}: proto has {key!r}, the class does not")
        elif key == "description":
            if not isinstance(got[key], str) or not got[key].strip():
                problems.append(f"{where}: proto needs a description")
        elif isinstance(want[key], dict) and isinstance(got[key], dict):
            _compare(f"{where}.{key}", want[key], got[key], problems)
        elif not _same(want[key], got[key]):
            problems.append(f"{where}.{key}: class has {want[key]!r}, proto has {got[key]!r}")


def differences(cls: type[Message], proto: dict) -> list[str]:
    """Every disagreement between ``cls`` and its loaded proto schema (empty = in sync)."""
    problems: list[str] = []
    _compare(cls.SPEC.type, schema_of(cls), proto, problems)
    return problems


def dump_draft(directory: str | Path) -> None:
    """Write a YAML draft per message type (a starting point; proto/ itself is hand-edited)."""
    for name, cls in REGISTRY.items():
        path = Path(directory) / f"{name.lower()}.yaml"
        path.write_text(yaml.safe_dump(schema_of(cls), sort_keys=False, width=110))
