"""Traffic counters, sequence tracking and rate-limited drop logging for bus endpoints.

Counters are plain dicts updated by the endpoint's own thread; a heartbeat thread reads
them through :meth:`Traffic.snapshot` (a dict copy is atomic under the GIL).
"""

from __future__ import annotations

import logging
import time
from collections import Counter, OrderedDict
from dataclasses import dataclass, field


@dataclass
class Traffic:
    """What one publisher or subscriber has moved and dropped."""

    messages: dict[str, int] = field(default_factory=dict)  # per topic
    bytes: dict[str, int] = field(default_factory=dict)  # per topic, payload (header + buffers)
    drops: Counter = field(default_factory=Counter)  # per reason (spec.DROP_REASONS)
    duplicates: int = 0  # repeats of an already delivered message (e.g. latched replays), skipped
    restarts: int = 0  # a source's seq went backwards: it restarted
    errors: int = 0
    last_error: str = ""

    def count(self, topic: str, nbytes: int) -> None:
        self.messages[topic] = self.messages.get(topic, 0) + 1
        self.bytes[topic] = self.bytes.get(topic, 0) + nbytes

    def drop(self, reason: str, n: int = 1) -> None:
        self.drops[reason] += n

    def error(self, text: str) -> None:
        self.errors += 1
        self.last_error = text.splitlines()[0][:500] if text else ""

    def snapshot(self) -> dict:
        return {
            "messages": dict(self.messages),
            "bytes": dict(self.bytes),
            "drops": dict(self.drops),
            "duplicates": self.duplicates,
            "restarts": self.restarts,
            "errors": self.errors,
            "last_error": self.last_error,
        }


class SeqTracker:
    """Last sequence number per (topic, src): classifies each arrival.

    Returns ('ok', 0) for the next expected or a first message, ('gap', n) when n messages
    are missing before it, ('duplicate', 0) for a repeat of the last one (a latched value
    replayed by the broker), ('restart', 0) when the source's seq went backwards.
    Bounded: the least recently seen entries are forgotten beyond ``max_entries``.
    """

    def __init__(self, max_entries: int = 4096):
        self._last: OrderedDict[tuple[str, str], int] = OrderedDict()
        self._max = max_entries

    def check(self, topic: str, src: str, seq: int) -> tuple[str, int]:
        key = (topic, src)
        last = self._last.get(key)
        if last is not None and seq == last:
            return "duplicate", 0
        self._last[key] = seq
        self._last.move_to_end(key)
        if len(self._last) > self._max:
            self._last.popitem(last=False)
        if last is None or seq == last + 1:
            return "ok", 0
        if seq > last:
            return "gap", seq - last - 1
        return "restart", 0


class DropLog:
    """Logs dropped messages at most once per source per ``interval_s``, with a count of the
    drops it kept quiet about. A flood of bad messages from one peer costs one line per
    interval; other sources still get their first line at once."""

    def __init__(
        self, logger: logging.Logger, interval_s: float = 10.0, max_sources: int = 1024, clock=time.monotonic
    ):
        self._log = logger
        self._interval = interval_s
        self._max = max_sources
        self._clock = clock
        self._state: dict[str, list] = {}  # source -> [last_log_time, suppressed Counter]

    def __call__(self, source: str, reason: str, detail: str) -> None:
        now = self._clock()
        state = self._state.get(source)
        if state is None:
            if len(self._state) >= self._max:
                source = "<other sources>"
                state = self._state.get(source)
            if state is None:
                state = self._state[source] = [None, Counter()]
        last, suppressed = state
        if last is not None and now - last < self._interval:
            suppressed[reason] += 1
            return
        extra = ""
        if suppressed:
            summary = ", ".join(f"{n} {r}" for r, n in suppressed.most_common())
            extra = f" (+{sum(suppressed.values())} more since the last report: {summary})"
        self._log.warning("dropped a message from %s: %s%s", source, detail, extra)
        state[0] = now
        suppressed.clear()
