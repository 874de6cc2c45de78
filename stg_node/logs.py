"""One logging setup for every entry point: level from STG_LOG_LEVEL, one line per record.

Library modules only call ``logging.getLogger(__name__)``; entry points (CLIs, nodes,
tools) call :func:`configure_logging` once.
"""

from __future__ import annotations

import logging
import os
import sys

ENV_LEVEL = "STG_LOG_LEVEL"
DEFAULT_LEVEL = "INFO"
LOG_FORMAT = "%(asctime)s.%(msecs)03d %(levelname)-7s %(processName)s %(name)s: %(message)s"
DATE_FORMAT = "%H:%M:%S"

_HANDLER_MARK = "_stg_node_handler"


class _Handler(logging.StreamHandler):
    """A StreamHandler that, unless given a stream, writes to ``sys.stderr`` as it is at each
    record (like logging.lastResort): redirections and test capture made after logging was
    configured still get the lines, and a replaced stderr is never written to after closing."""

    def __init__(self, stream=None):
        super().__init__(stream)  # sets self.stream (to sys.stderr when None) through the setter
        self._fixed = stream

    @property
    def stream(self):
        return self._fixed if self._fixed is not None else sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        self._fixed = value


def parse_level(value: str | int | None) -> int:
    """Turn 'debug', 'INFO', '10' or 10 into a logging level; a clear error otherwise."""
    if value is None or value == "":
        value = DEFAULT_LEVEL
    if isinstance(value, int):
        return value
    text = str(value).strip()
    if text.isdigit():
        return int(text)
    level = logging.getLevelName(text.upper())
    if not isinstance(level, int):
        raise ValueError(
            f"unknown log level {value!r} (from {ENV_LEVEL} or --log-level); "
            "use DEBUG, INFO, WARNING, ERROR, CRITICAL or a number"
        )
    return level


def configure_logging(level: str | int | None = None, stream=None) -> int:
    """Configure the root logger once; later calls only change the level.

    ``level`` wins over ``STG_LOG_LEVEL``, which wins over INFO. Returns the level set.
    """
    resolved = parse_level(level if level is not None else os.environ.get(ENV_LEVEL))
    root = logging.getLogger()
    ours = [h for h in root.handlers if getattr(h, _HANDLER_MARK, False)]
    if not ours:
        handler = _Handler(stream)
        handler.setFormatter(logging.Formatter(LOG_FORMAT, DATE_FORMAT))
        setattr(handler, _HANDLER_MARK, True)
        root.addHandler(handler)
    elif stream is not None:
        ours[0].setStream(stream)
    root.setLevel(resolved)
    return resolved
