"""Typed node parameters: a dataclass per node kind, filled from a launch file or the command line.

    @dataclass
    class IngestParams:
        path: str = param(doc="dataset folder or video file")
        rate_hz: float = param(30.0, min=0.0, unit="Hz", doc="publishing rate; 0 = as fast as consumed")

:func:`parse_params` turns a mapping (launch-file YAML, ``--params`` JSON, ``--param k=v`` text)
into that dataclass: unknown names, missing required ones, wrong types and out-of-range values
raise :class:`ParamError` naming the node and the parameter. Strings are coerced to the declared
type (launch-file substitutions and ``k=v`` always produce text). :func:`describe_params` and
:func:`params_json_schema` describe a class for docs and for the launch-file schema.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import math
import types
import typing
from dataclasses import dataclass
from typing import Any, Literal

import yaml

_MISSING = dataclasses.MISSING
_TRUE = {"true", "yes", "on", "1"}
_FALSE = {"false", "no", "off", "0"}
_NONE = {"", "null", "none", "~"}


class ParamError(ValueError):
    """A node parameter is unknown, missing, of the wrong type or out of range."""

    def __init__(self, where: str, name: str | None, problem: str):
        self.where = where
        self.name = name
        self.problem = problem
        what = f"param {name!r}: " if name else ""
        super().__init__(f"{where}: {what}{problem}")


@dataclass(frozen=True)
class ParamSpec:
    """What :func:`param` records about one field, beyond its type and default."""

    doc: str = ""
    unit: str = ""
    min: float | None = None
    max: float | None = None


def param(default=_MISSING, *, doc: str = "", unit: str = "", min=None, max=None):
    """A parameter field. Without ``default`` it is required; lists and dicts are copied per instance."""
    meta = {"param": ParamSpec(doc=doc, unit=unit, min=min, max=max)}
    if default is _MISSING:
        return dataclasses.field(metadata=meta)
    if isinstance(default, (list, dict)):
        return dataclasses.field(default_factory=lambda: type(default)(default), metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


@dataclass
class NoParams:
    """For nodes without parameters."""


def _spec(f: dataclasses.Field) -> ParamSpec:
    return f.metadata.get("param", ParamSpec())


def _type_name(tp) -> str:
    origin = typing.get_origin(tp)
    if origin is Literal:
        return " | ".join(repr(a) for a in typing.get_args(tp))
    if origin in (typing.Union, types.UnionType):
        return " | ".join(_type_name(a) for a in typing.get_args(tp))
    if origin in (list, tuple, dict):
        args = [a for a in typing.get_args(tp) if a is not Ellipsis]
        return f"{origin.__name__}[{', '.join(_type_name(a) for a in args)}]"
    if tp is type(None):
        return "null"
    return getattr(tp, "__name__", str(tp))


def _parse_text(text: str):
    """A YAML scalar or flow collection from text ('3', '[1, 2]', '{a: 1}'); the text itself if not YAML."""
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        return text


def _number(text: str):
    """int or float from text ('3', '1e3', '-inf'); the text itself when it is neither."""
    text = text.strip()
    try:
        return int(text)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        return text


def coerce(value: Any, tp, name: str, where: str) -> Any:
    """``value`` as type ``tp`` (str, int, float, bool, X | None, Literal, list[X], tuple[X, ...],
    dict[str, X]); a :class:`ParamError` naming ``name`` if it cannot be."""

    def fail(expected: str):
        raise ParamError(where, name, f"must be {expected}, got {value!r}")

    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        options = typing.get_args(tp)
        if type(None) in options and (value is None or (isinstance(value, str) and value.lower() in _NONE)):
            return None
        others = [o for o in options if o is not type(None)]
        if len(others) == 1:  # X | None: X's own, more precise error
            return coerce(value, others[0], name, where)
        for option in others:
            try:
                return coerce(value, option, name, where)
            except ParamError:
                continue
        fail(_type_name(tp))
    if origin is Literal:
        choices = typing.get_args(tp)
        for choice in choices:
            if value == choice or (isinstance(value, (int, float)) and str(value) == str(choice)):
                return choice
        fail(f"one of {', '.join(repr(c) for c in choices)}")
    if origin in (list, tuple):
        if isinstance(value, str):
            parsed = _parse_text(value)
            value = parsed if isinstance(parsed, list) else [v.strip() for v in value.split(",") if v.strip()]
        if not isinstance(value, (list, tuple)):
            fail(f"a list ({_type_name(tp)})")
        args = typing.get_args(tp)
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                fail(f"a list of {len(args)} values ({_type_name(tp)})")
            return tuple(
                coerce(v, a, f"{name}[{i}]", where) for i, (v, a) in enumerate(zip(value, args, strict=True))
            )
        item = args[0] if args else Any
        items = [coerce(v, item, f"{name}[{i}]", where) for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin is dict:
        if isinstance(value, str):
            value = _parse_text(value)
        if not isinstance(value, dict):
            fail(f"a mapping ({_type_name(tp)})")
        key_tp, value_tp = typing.get_args(tp) or (str, Any)
        return {
            coerce(k, key_tp, f"{name} key", where): coerce(v, value_tp, f"{name}.{k}", where)
            for k, v in value.items()
        }
    if tp is Any:
        return value
    if tp is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.strip().lower() in _TRUE | _FALSE:
            return value.strip().lower() in _TRUE
        fail("true or false")
    if tp is int:
        if isinstance(value, str):
            value = _number(value)
        if isinstance(value, bool):
            fail("an integer")
        if isinstance(value, int):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        fail("an integer")
    if tp is float:
        if isinstance(value, str):
            value = _number(value)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or math.isnan(value):
            fail("a number")
        return float(value)
    if tp is str:
        if isinstance(value, str):
            return value
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return str(value)
        if isinstance(value, bool):  # YAML reads true/yes/on as booleans
            raise ParamError(where, name, f"must be text, got {value!r} (quote it: '{str(value).lower()}')")
        fail("text")
    raise TypeError(f"{where}: param {name!r} has a type params cannot parse: {tp!r}")


def parse_params(cls: type, values: dict | None, *, where: str = "node"):
    """An instance of the params dataclass ``cls`` from ``values``; :class:`ParamError` on bad input.

    Runs the class's ``validate()`` (if any) after the per-field checks; it may raise ParamError
    or ValueError (re-raised as ParamError for ``where``).
    """
    values = dict(values or {})
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    unknown = sorted(set(values) - set(fields))
    if unknown:
        name = unknown[0]
        close = difflib.get_close_matches(name, fields, n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        known = ", ".join(fields) or "none"
        raise ParamError(where, name, f"unknown parameter{hint} (known: {known})")
    kwargs = {}
    for name, f in fields.items():
        if name not in values:
            if f.default is _MISSING and f.default_factory is _MISSING:
                doc = _spec(f).doc
                raise ParamError(
                    where, name, f"required ({_type_name(hints[name])}{': ' + doc if doc else ''})"
                )
            continue
        value = coerce(values[name], hints[name], name, where)
        spec = _spec(f)
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if spec.min is not None and value < spec.min:
                raise ParamError(where, name, f"must be >= {spec.min}, got {value}")
            if spec.max is not None and value > spec.max:
                raise ParamError(where, name, f"must be <= {spec.max}, got {value}")
        kwargs[name] = value
    instance = cls(**kwargs)
    validate = getattr(instance, "validate", None)
    if validate is not None:
        try:
            validate()
        except ParamError:
            raise
        except ValueError as exc:
            raise ParamError(where, None, str(exc)) from exc
    return instance


@dataclass(frozen=True)
class ParamInfo:
    """One parameter, as documentation shows it."""

    name: str
    type: str
    default: Any  # dataclasses.MISSING-free: None with required=True when there is none
    required: bool
    doc: str
    unit: str


def describe_params(cls: type) -> list[ParamInfo]:
    hints = typing.get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        spec = _spec(f)
        if f.default is not _MISSING:
            default, required = f.default, False
        elif f.default_factory is not _MISSING:
            default, required = f.default_factory(), False
        else:
            default, required = None, True
        out.append(ParamInfo(f.name, _type_name(hints[f.name]), default, required, spec.doc, spec.unit))
    return out


def params_markdown(cls: type) -> str:
    """A markdown table of the parameters (docs/NODES.md holds one per node kind; a test compares)."""
    rows = ["| param | type | default | meaning |", "|---|---|---|---|"]
    for info in describe_params(cls):
        default = "required" if info.required else f"`{json.dumps(info.default)}`"
        unit = f" [{info.unit}]" if info.unit else ""
        kind = info.type.replace("|", "\\|")
        rows.append(f"| `{info.name}` | {kind} | {default} | {info.doc}{unit} |")
    return "\n".join(rows)


_SUBSTITUTION = {"type": "string", "pattern": r"\$\("}


def _json_type(tp) -> dict:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        return {"anyOf": [_json_type(a) for a in typing.get_args(tp)]}
    if origin is Literal:
        return {"enum": list(typing.get_args(tp))}
    if origin in (list, tuple):
        args = [a for a in typing.get_args(tp) if a is not Ellipsis]
        return {"type": "array", "items": _json_type(args[0]) if args else {}}
    if origin is dict:
        args = typing.get_args(tp)
        return {"type": "object", "additionalProperties": _json_type(args[1]) if args else {}}
    return {
        bool: {"type": "boolean"},
        int: {"type": "integer"},
        float: {"type": "number"},
        str: {"type": "string"},
        type(None): {"type": "null"},
    }.get(tp, {})


def params_json_schema(cls: type) -> dict:
    """JSON schema of a params mapping (values may also be ``$(...)`` substitutions, checked later)."""
    hints = typing.get_type_hints(cls)
    properties = {}
    required = []
    for f in dataclasses.fields(cls):
        spec = _spec(f)
        prop = dict(_json_type(hints[f.name]))
        if spec.min is not None:
            prop["minimum"] = spec.min
        if spec.max is not None:
            prop["maximum"] = spec.max
        description = spec.doc + (f" [{spec.unit}]" if spec.unit else "")
        properties[f.name] = {"anyOf": [prop, _SUBSTITUTION], "description": description}
        if f.default is _MISSING and f.default_factory is _MISSING:
            required.append(f.name)
    schema = {"type": "object", "properties": properties, "additionalProperties": False}
    if required:
        schema["required"] = required
    return schema
