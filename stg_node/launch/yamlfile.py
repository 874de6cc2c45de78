"""Reading a launch file: PyYAML's safe loader, plus the line of every value for error messages.

``yaml.safe_load`` returns plain dicts that forget where things were. We run the same
SafeLoader in two steps (compose the node graph, then construct it, as safe_load does
internally), and walk the node graph beside the result to remember each value's line. Safe:
SafeLoader constructs only plain YAML types; no tag can create an object. Duplicate keys
(which PyYAML silently overwrites) are refused with both lines.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import yaml


class LaunchFileError(ValueError):
    """A launch file is malformed; names the file and line where possible."""

    def __init__(self, path: str | Path | None, line: int | None, problem: str):
        self.path = None if path is None else Path(path)
        self.line = line
        self.problem = problem
        where = str(self.path) if self.path is not None else "<launch>"
        if line is not None:
            where += f":{line}"
        super().__init__(f"{where}: {problem}")


Key = tuple  # a path into the document: ("nodes", 2, "params", "rate_hz")


@dataclass
class Located:
    """A loaded YAML document and the 1-based line of each value in it."""

    path: Path
    data: object
    lines: dict[Key, int] = field(default_factory=dict)

    def line(self, key: Key) -> int | None:
        """The line of ``key``, else of its closest enclosing value."""
        key = tuple(key)
        while key:
            if key in self.lines:
                return self.lines[key]
            key = key[:-1]
        return self.lines.get((), 1)

    def error(self, key: Key, problem: str) -> LaunchFileError:
        return LaunchFileError(self.path, self.line(key), problem)


def _walk(node: yaml.Node, key: Key, lines: dict, path: Path) -> None:
    lines[key] = node.start_mark.line + 1
    if isinstance(node, yaml.MappingNode):
        seen: dict = {}
        for key_node, value_node in node.value:
            name = key_node.value if isinstance(key_node, yaml.ScalarNode) else None
            if name in seen:
                raise LaunchFileError(
                    path,
                    key_node.start_mark.line + 1,
                    f"key {name!r} appears twice in one mapping (first on line {seen[name]})",
                )
            seen[name] = key_node.start_mark.line + 1
            _walk(value_node, (*key, name), lines, path)
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            _walk(item, (*key, i), lines, path)


def load_text(text: str, path: str | Path) -> Located:
    path = Path(path)
    loader = yaml.SafeLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return Located(path, None, {(): 1})
        lines: dict = {}
        _walk(node, (), lines, path)
        data = loader.construct_document(node)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark is not None else None
        problem = " ".join(str(p) for p in (exc.context, exc.problem) if p)
        raise LaunchFileError(path, line, f"not valid YAML: {problem}") from exc
    except yaml.YAMLError as exc:
        raise LaunchFileError(path, None, f"not valid YAML: {exc}") from exc
    finally:
        loader.dispose()
    return Located(path, data, lines)


def load_file(path: str | Path) -> Located:
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise LaunchFileError(path, None, "no such launch file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise LaunchFileError(path, None, f"cannot be read: {exc}") from exc
    return load_text(text, path)
