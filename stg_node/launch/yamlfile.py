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


#: A launch file is a few hundred values; YAML aliases can make a small file expand to billions
#: (an "alias bomb"), which everything that walks the document would then walk. Refused beyond this.
MAX_VALUES = 100_000
#: Deeper than this is not a launch file (and would exhaust Python's recursion further on).
MAX_DEPTH = 64


def _expanded_size(node: yaml.Node, path: Path) -> int:
    """How many values ``node`` stands for once its aliases are expanded (shared nodes counted once
    per use, computed once per node); a LaunchFileError past MAX_VALUES or MAX_DEPTH."""
    sizes: dict[int, int] = {}
    stack: list[tuple[yaml.Node, int, bool]] = [(node, 0, False)]
    while stack:
        current, depth, children_done = stack.pop()
        if id(current) in sizes:
            continue
        if depth > MAX_DEPTH:
            raise LaunchFileError(path, current.start_mark.line + 1, f"nested deeper than {MAX_DEPTH} levels")
        if isinstance(current, yaml.MappingNode):
            children = [n for pair in current.value for n in pair]
        elif isinstance(current, yaml.SequenceNode):
            children = list(current.value)
        else:
            children = []
        if not children_done and any(id(c) not in sizes for c in children):
            stack.append((current, depth, True))
            stack.extend((c, depth + 1, False) for c in children if id(c) not in sizes)
            continue
        sizes[id(current)] = 1 + sum(sizes[id(c)] for c in children)
        if sizes[id(current)] > MAX_VALUES:
            raise LaunchFileError(
                path,
                current.start_mark.line + 1,
                f"expands to more than {MAX_VALUES} values (YAML aliases repeating aliases?); "
                "a launch file is a few hundred",
            )
    return sizes[id(node)]


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
        _expanded_size(node, path)  # before anything walks it
        lines: dict = {}
        _walk(node, (), lines, path)
        data = loader.construct_document(node)
    except RecursionError:  # PyYAML composes recursively: a document nested thousands deep
        raise LaunchFileError(
            path, None, f"not valid YAML: nested far deeper than {MAX_DEPTH} levels"
        ) from None
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
