"""Traffic counters and the rates computed from them; sequence tracking; rate-limited drop logging.

Counters are plain dicts updated by the endpoint's own thread; a heartbeat thread reads
them through :meth:`Traffic.snapshot` (a dict copy is atomic under the GIL).

Rates have one definition, used by every reporter: the messages (bytes) that arrived in
an interval ``(t0, t1]``, divided by ``t1 - t0`` (:func:`per_second`). A node's heartbeat
and the broker (NodeStatus ``rates_hz`` / ``bytes_per_s``) take the interval since their
previous status (:class:`RateMeter`, from cumulative counters, nothing per message);
``stg-topic hz`` / ``bw`` take the span of their last N arrivals (:class:`ArrivalWindow`:
the messages after the first one, over the time from the first to the last). On the same
stream over the same interval the two give the same numbers (tests/bus/test_bus_stats.py).
``stg-topic list`` summarises everything seen while it listened (:class:`TopicCensus`).
"""

from __future__ import annotations

import logging
import statistics
import time
from collections import Counter, OrderedDict, deque
from collections.abc import Mapping
from dataclasses import dataclass, field

#: Shortest interval a rate is computed over: a rate stays finite (NodeStatus requires it)
#: even for two samples at the same clock reading.
MIN_INTERVAL_S = 1e-6


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


# --- rates ----------------------------------------------------------------------------------------


def per_second(amount: float, seconds: float) -> float:
    """``amount`` that arrived over ``seconds``, per second: the one rate formula of the bus."""
    return amount / max(seconds, MIN_INTERVAL_S)


def format_bytes(nbytes: float | None) -> str:
    """A byte count for people, in decimal units: ``603B``, ``180.82KB``, ``6.22MB`` (``?``: unknown).
    The one size format of the bus tools (stg-topic, stg-bag)."""
    if nbytes is None:
        return "?"
    for unit in ("B", "KB", "MB", "GB"):
        if abs(nbytes) < 1000 or unit == "GB":
            return f"{nbytes:.2f}{unit}" if unit != "B" else f"{nbytes:.0f}B"
        nbytes /= 1000
    return f"{nbytes:.2f}GB"


@dataclass(frozen=True)
class TopicRates:
    """Per-topic rates over one interval (what NodeStatus carries)."""

    rates_hz: dict[str, float]  # messages per second, per topic
    bytes_per_s: dict[str, float]  # payload bytes (header + buffers) per second, per topic
    interval_s: float  # the interval they were measured over


class RateMeter:
    """Per-topic rates from cumulative counters, over the interval since the previous sample.

    Costs nothing per message: the endpoints keep counting in :class:`Traffic`, and a
    reporter (the heartbeat, the broker) samples the counters once per status period.
    ``clock`` is injectable for tests; the interval starts at construction.
    """

    def __init__(self, clock=time.monotonic):
        self._clock = clock
        self._messages: Mapping[str, int] = {}
        self._bytes: Mapping[str, int] = {}
        self._time = clock()

    def sample(self, messages: Mapping[str, int], nbytes: Mapping[str, int]) -> TopicRates:
        """Rates of every topic in the counters since the last sample (or construction)."""
        now = self._clock()
        dt = now - self._time
        prev_msgs, prev_bytes = self._messages, self._bytes
        rates = {t: per_second(n - prev_msgs.get(t, 0), dt) for t, n in messages.items()}
        bandwidth = {t: per_second(b - prev_bytes.get(t, 0), dt) for t, b in nbytes.items()}
        self._messages, self._bytes, self._time = dict(messages), dict(nbytes), now
        return TopicRates(rates_hz=rates, bytes_per_s=bandwidth, interval_s=max(dt, MIN_INTERVAL_S))


@dataclass(frozen=True)
class WindowStats:
    """Rate and size statistics over the last arrivals of one topic (``stg-topic hz`` / ``bw``)."""

    arrivals: int  # messages in the window (gaps = arrivals - 1)
    span_s: float  # first to last arrival
    rate_hz: float  # messages after the first, per second of the span
    min_gap_s: float
    max_gap_s: float
    std_gap_s: float  # population standard deviation of the gaps (0 for one gap)
    bytes_per_s: float  # bytes of the messages after the first, per second of the span
    mean_bytes: float  # message sizes over the window's last ``size`` messages
    min_bytes: int
    max_bytes: int
    sized: int  # how many sizes the mean, min and max are over


class ArrivalWindow:
    """The last ``size`` gaps between arrivals of a topic (``size + 1`` arrival times) and the
    last ``size`` message sizes: a sliding window, as ``ros2 topic hz`` / ``bw`` keep."""

    def __init__(self, size: int = 100):
        if size < 1:
            raise ValueError(f"a rate window needs at least 1 message, got {size}")
        self.size = size
        self._times: deque[float] = deque(maxlen=size + 1)
        self._sizes: deque[int] = deque(maxlen=size)
        self.received = 0  # every arrival ever added

    def add(self, time_s: float, nbytes: int) -> None:
        """One message arrived at ``time_s`` (a monotonic clock) carrying ``nbytes`` of payload."""
        self._times.append(time_s)
        self._sizes.append(nbytes)
        self.received += 1

    def __len__(self) -> int:
        return len(self._times)

    def stats(self) -> WindowStats | None:
        """The window's statistics; None until two messages have arrived (no gap yet)."""
        times = list(self._times)
        if len(times) < 2:
            return None
        gaps = [b - a for a, b in zip(times[:-1], times[1:], strict=True)]
        span = times[-1] - times[0]
        sizes = list(self._sizes)
        after_first = sizes[-len(gaps) :]  # the messages that close each gap
        return WindowStats(
            arrivals=len(times),
            span_s=span,
            rate_hz=per_second(len(gaps), span),
            min_gap_s=min(gaps),
            max_gap_s=max(gaps),
            std_gap_s=statistics.pstdev(gaps) if len(gaps) > 1 else 0.0,
            bytes_per_s=per_second(sum(after_first), span),
            mean_bytes=statistics.fmean(sizes),
            min_bytes=min(sizes),
            max_bytes=max(sizes),
            sized=len(sizes),
        )


@dataclass(frozen=True)
class TopicSummary:
    """One topic as seen by ``stg-topic list`` over its listening time."""

    topic: str
    type: str
    messages: int
    rate_hz: float  # messages per second of listening
    mean_bytes: float
    sources: tuple[str, ...]  # src of the messages, sorted


class TopicCensus:
    """Every topic seen while listening: type, message count, bytes, sources.

    Bounded against peers inventing topics or source names: beyond ``max_topics`` topics
    (``max_sources`` sources per topic) new ones are counted under ``<other>``.
    """

    def __init__(self, max_topics: int = 1024, max_sources: int = 64):
        self._max_topics = max_topics
        self._max_sources = max_sources
        self._topics: dict[str, list] = {}  # topic -> [type, messages, bytes, set of src]

    def add(self, topic: str, type_name: str, nbytes: int, src: str) -> None:
        entry = self._topics.get(topic)
        if entry is None:
            if len(self._topics) >= self._max_topics:
                topic, type_name = "<other>", "?"
            entry = self._topics.setdefault(topic, [type_name, 0, 0, set()])
        entry[1] += 1
        entry[2] += nbytes
        sources = entry[3]
        if src in sources or len(sources) < self._max_sources:
            sources.add(src)
        else:
            sources.add("<other>")

    def __len__(self) -> int:
        return len(self._topics)

    def summary(self, seconds: float) -> list[TopicSummary]:
        """Every topic, sorted by name, with its rate over ``seconds`` of listening."""
        return [
            TopicSummary(
                topic=topic,
                type=type_name,
                messages=count,
                rate_hz=per_second(count, seconds),
                mean_bytes=nbytes / count,
                sources=tuple(sorted(sources)),
            )
            for topic, (type_name, count, nbytes, sources) in sorted(self._topics.items())
        ]
