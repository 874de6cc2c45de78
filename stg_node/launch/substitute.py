"""Substitutions in launch-file strings: ``$(arg NAME)``, ``$(env NAME [DEFAULT])``, ``$(exists PATH)``,
``$(nonempty TEXT)``, ``$(nonzero NUMBER)``, ``$(dirname)``, ``$(python)``.
They nest (``$(exists $(arg out)/subject)``); inner ones first.

| form | value |
|---|---|
| ``$(arg NAME)`` | the launch argument (command line ``NAME:=VALUE``, include ``args:``, or its default) |
| ``$(env NAME)`` / ``$(env NAME DEFAULT)`` | an environment variable; an error if unset and no default |
| ``$(exists PATH)`` | ``true`` if the file or folder exists, else ``false`` (for ``if:`` / ``unless:``) |
| ``$(nonempty TEXT)`` | ``true`` if TEXT is not empty, else ``false``: ``if: $(nonempty $(arg record))`` |
| ``$(nonzero NUMBER)`` | ``true`` if NUMBER is a number but 0, else ``false``: ``if: $(nonzero $(arg x))`` |
| ``$(dirname)`` | the folder of the launch file being read (for paths relative to it) |
| ``$(python)`` | the Python interpreter running stg-launch |
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from pathlib import Path

START = "$("


class SubstitutionError(ValueError):
    """A substitution is malformed or names an unknown argument or unset variable."""


@dataclass(frozen=True)
class Scope:
    """What substitutions resolve against: the file's arguments and its folder."""

    args: dict[str, str]
    dirname: Path


def _matching_paren(text: str, open_at: int) -> int:
    depth = 0
    for i in range(open_at, len(text)):
        if text[i] == "(":
            depth += 1
        elif text[i] == ")":
            depth -= 1
            if depth == 0:
                return i
    raise SubstitutionError(f"unclosed '$(' in {text!r}")


def _evaluate(expr: str, scope: Scope) -> str:
    parts = expr.split()
    if not parts:
        raise SubstitutionError("empty substitution '$()'")
    verb, rest = parts[0], parts[1:]
    if verb == "arg":
        if len(rest) != 1:
            raise SubstitutionError(f"$(arg NAME) takes one name, got $({expr})")
        if rest[0] not in scope.args:
            known = ", ".join(sorted(scope.args)) or "none"
            raise SubstitutionError(f"$(arg {rest[0]}): no such launch argument (declared: {known})")
        return scope.args[rest[0]]
    if verb == "env":
        if len(rest) not in (1, 2):
            raise SubstitutionError(
                f"$(env NAME [DEFAULT]) takes a name and an optional default, got $({expr})"
            )
        value = os.environ.get(rest[0])
        if value is None:
            if len(rest) == 2:
                return rest[1]
            raise SubstitutionError(f"$(env {rest[0]}): the environment variable is not set (give a default)")
        return value
    if verb == "exists":
        if len(rest) != 1:
            raise SubstitutionError(f"$(exists PATH) takes one path, got $({expr})")
        path = Path(rest[0]).expanduser()
        if not path.is_absolute():
            path = Path.cwd() / path
        return "true" if path.exists() else "false"
    if verb == "nonempty":
        return "true" if rest else "false"
    if verb == "nonzero":
        if len(rest) > 1:
            raise SubstitutionError(f"$(nonzero NUMBER) takes one number, got $({expr})")
        if not rest:
            return "false"
        try:
            return "true" if float(rest[0]) != 0 else "false"
        except ValueError:
            raise SubstitutionError(f"$(nonzero NUMBER): {rest[0]!r} is not a number") from None
    if verb == "dirname":
        return str(scope.dirname)
    if verb == "python":
        return sys.executable
    raise SubstitutionError(
        f"unknown substitution $({expr}); use arg, env, exists, nonempty, nonzero, dirname or python"
    )


def substitute(text: str, scope: Scope) -> str:
    """``text`` with every ``$(...)`` replaced, innermost first."""
    if START not in text:
        return text
    out = []
    i = 0
    while True:
        start = text.find(START, i)
        if start < 0:
            out.append(text[i:])
            return "".join(out)
        out.append(text[i:start])
        end = _matching_paren(text, start + 1)
        inner = substitute(text[start + 2 : end], scope)
        out.append(_evaluate(inner, scope))
        i = end + 1


def substitute_all(value, scope: Scope):
    """Substitute in every string of a nested structure of dicts, lists and scalars."""
    if isinstance(value, str):
        return substitute(value, scope)
    if isinstance(value, dict):
        return {k: substitute_all(v, scope) for k, v in value.items()}
    if isinstance(value, list):
        return [substitute_all(v, scope) for v in value]
    return value
