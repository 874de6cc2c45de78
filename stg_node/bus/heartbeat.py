"""Heartbeats: a node's NodeStatus, published every period from a thread; and who is alive.

:class:`Heartbeat` merges the traffic counters of a node's publishers and subscribers
(messages and bytes per topic, drops per reason, errors) into a NodeStatus and publishes
it on ``node/status`` through the node's (thread-safe) Publisher, even while the node's
own loop is busy in a long computation. A last status with state ``stopping`` goes out
when it stops. :class:`NodeMonitor` turns received heartbeats into alive / silent nodes
(silent = nothing for ``missed`` periods).
"""

from __future__ import annotations

import logging
import os
import socket as pysocket
import threading
import time
from collections import Counter

from stg_node.bus.messages import NODE_STATES, NodeStatus
from stg_node.bus.pubsub import Publisher, Subscriber
from stg_node.bus.stats import RateMeter, Traffic

log = logging.getLogger(__name__)


class Heartbeat:
    """Publishes a NodeStatus for ``publisher.node`` every ``period_s`` seconds.

    Rates are over the interval since the previous status (stats.RateMeter); ``clock`` (a
    monotonic clock in seconds) is injectable for tests."""

    def __init__(self, publisher: Publisher, sources=(), *, period_s: float = 1.0, clock=time.monotonic):
        if period_s <= 0:
            raise ValueError(f"heartbeat period must be > 0 s, got {period_s}")
        self.publisher = publisher
        self.period_s = period_s
        self.traffic = Traffic()  # the node's own errors / drops, beyond its endpoints'
        self._sources: list = [publisher, *sources]
        self._state = "starting"
        self._clock = clock
        self._started = clock()
        self._rates = RateMeter(clock)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._host = pysocket.gethostname()

    def add(self, source: Publisher | Subscriber) -> None:
        self._sources.append(source)

    @property
    def state(self) -> str:
        return self._state

    @state.setter
    def state(self, value: str) -> None:
        if value not in NODE_STATES:
            raise ValueError(f"node state {value!r} is not one of {NODE_STATES}")
        self._state = value

    def error(self, text: str) -> None:
        """Record a node-level error (shows in the next NodeStatus)."""
        self.traffic.error(text)

    def status(self) -> NodeStatus:
        """The NodeStatus as of now (also advances the rate window)."""
        published: Counter = Counter()
        received: Counter = Counter()
        nbytes: Counter = Counter()
        drops: Counter = Counter(self.traffic.drops)
        errors, last_error = self.traffic.errors, self.traffic.last_error
        for source in self._sources:
            snap = source.traffic.snapshot()
            (published if isinstance(source, Publisher) else received).update(snap["messages"])
            nbytes.update(snap["bytes"])
            drops.update(snap["drops"])
            errors += snap["errors"]
            last_error = snap["last_error"] or last_error
        rates = self._rates.sample(published + received, nbytes)
        return NodeStatus(
            node=self.publisher.node,
            state=self._state,
            pid=os.getpid(),
            host=self._host,
            uptime_s=self._clock() - self._started,
            period_s=self.period_s,
            published=dict(published),
            received=dict(received),
            rates_hz=rates.rates_hz,
            bytes_per_s=rates.bytes_per_s,
            drops=dict(drops),
            errors=errors,
            last_error=last_error,
        )

    def beat(self) -> None:
        try:
            self.publisher.publish(self.status())
        except Exception as exc:  # a status that cannot be sent must not kill the node
            log.warning("heartbeat not published: %s", exc)

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            self.beat()

    def start(self) -> Heartbeat:
        if self._state == "starting":
            self._state = "running"
        if self._thread is None:
            self.beat()
            self._thread = threading.Thread(target=self._run, name="stg-heartbeat", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
            self._state = "stopping"
            self.beat()

    def __enter__(self) -> Heartbeat:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


class NodeMonitor:
    """Which nodes are alive, from their NodeStatus heartbeats."""

    def __init__(self, missed: int = 3, clock=time.monotonic):
        self.missed = missed
        self._clock = clock
        self.nodes: dict[str, tuple[NodeStatus, float]] = {}

    def update(self, status: NodeStatus) -> None:
        self.nodes[status.node] = (status, self._clock())

    def silent(self) -> list[str]:
        """Nodes not heard from for ``missed`` periods, or whose last word was 'stopping'."""
        now = self._clock()
        return sorted(
            node
            for node, (status, seen) in self.nodes.items()
            if status.state == "stopping" or now - seen > self.missed * max(status.period_s, 1e-3)
        )

    def alive(self) -> list[str]:
        gone = set(self.silent())
        return sorted(node for node in self.nodes if node not in gone)
