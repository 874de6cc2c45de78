"""Recorder: everything that crosses the bus, into an MCAP recording, with drops counted.

    recorder = Recorder("session.mcap", config=BusConfig.from_env(), compression="zstd").start()
    while running:
        recorder.poll(0.2)          # writes what arrived; flushes a chunk at least every second
    stats = recorder.stop()         # drains, finishes the file(s): summary, counts, drops

A reader thread owns a whole-bus Subscriber (every lane, ``keep_last=False``: on the
keep-last lane too, every message that reaches us, in order; latched values arrive when it
subscribes) and only receives: each message goes, with its receive time, into a queue in
memory. The caller's thread writes the queue to disk in :meth:`poll`. So a slow disk
moment or a chunk being compressed never stalls the socket reads: the keep-last lane's
queues are 4 messages deep at every hop and drop the newest message when full, so a
recorder that read only between writes would lose camera frames.

Drops are counted, never hidden: the subscriber's counters (``lost`` = sequence gaps, i.e.
messages that never reached us; ``malformed`` etc. = refused by the envelope checks) plus
``recorder_overflow`` when the queue holds ``max_queue_bytes`` and the disk cannot keep up.
They are in :meth:`stats` and in the recording's ``stg.recording.end`` metadata.
"""

from __future__ import annotations

import itertools
import json
import logging
import re
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import zmq

from stg_node.bus import BusConfig, Subscriber
from stg_node.bus.config import as_config
from stg_node.bus.recording.format import RecordingError
from stg_node.bus.recording.writer import DEFAULT_CHUNK_SIZE, DEFAULT_FLUSH_INTERVAL_S, BagWriter

log = logging.getLogger(__name__)

MiB = 1 << 20
DEFAULT_MAX_QUEUE_BYTES = 512 * MiB
OVERFLOW = "recorder_overflow"
_POLL_MS = 1000  # the reader thread's longest wait; stop() wakes it earlier
_DRAIN_S = 1.0  # on stop: at most this long reading what had already arrived ...
_QUIET_S = 0.2  # ... until nothing more has come for this long
_ids = itertools.count()
_WRITE_SLICE_S = 0.5  # poll() returns after this long even with more queued, so callers stay responsive


@dataclass
class RecorderStats:
    """What a recorder has seen and written so far."""

    received: int = 0  # messages received that matched the topic filter
    written: int = 0
    bytes_written: int = 0  # payload (header + buffers)
    filtered: int = 0  # received but not matching --topics
    queued: int = 0
    queued_bytes: int = 0
    drops: dict[str, int] = field(default_factory=dict)  # reason -> count (bus reasons + recorder_overflow)
    duplicates: int = 0  # latched repeats skipped
    files: list[str] = field(default_factory=list)

    @property
    def dropped(self) -> int:
        return sum(self.drops.values())


def topic_matcher(patterns) -> callable | None:
    """A predicate for topics matching any of the regexes (searched, as ``ros2 bag record -e``)."""
    if not patterns:
        return None
    try:
        compiled = [re.compile(p) for p in patterns]
    except re.error as exc:
        raise RecordingError(f"bad topic pattern: {exc}") from None
    return lambda topic: any(p.search(topic) for p in compiled)


class Recorder:
    """Records the bus into ``path``; see the module docstring. ``start()``, ``poll()``, ``stop()``.

    ``topics``: regexes; only topics matching one are recorded (None: everything).
    ``config``: the bus (BusConfig, URL or None for the environment's). ``context``: a zmq
    context to share (a node's); by default the recorder owns one. ``launch_file`` and
    ``metadata`` go into the file (see BagWriter).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        config: BusConfig | str | None = None,
        topics=None,
        compression: str = "none",
        split_size: int | None = None,
        split_duration_s: float | None = None,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S,
        max_queue_bytes: int = DEFAULT_MAX_QUEUE_BYTES,
        launch_file: str | Path | None = None,
        metadata: dict[str, str] | None = None,
        context: zmq.Context | None = None,
    ):
        self.config = config = as_config(config)
        self.path = Path(path)
        self.topics = list(topics or [])
        self._match = topic_matcher(self.topics)
        self.max_queue_bytes = max_queue_bytes
        self._writer_options = dict(
            compression=compression,
            split_size=split_size,
            split_duration_s=split_duration_s,
            chunk_size=chunk_size,
            flush_interval_s=flush_interval_s,
            launch_file=launch_file,
            bus_config=config,
            end_info=self._end_info,
            metadata={
                "bus": config.url,
                "namespace": config.namespace,
                "topics": json.dumps(self.topics),
                **(metadata or {}),
            },
        )
        self._own_context = context is None
        self._context = context
        self._writer: BagWriter | None = None
        self._thread: threading.Thread | None = None
        self._subscriber: Subscriber | None = None
        self._cond = threading.Condition()
        self._queue: deque = deque()
        self._queued_bytes = 0
        self._stop = threading.Event()
        self._wake_endpoint = f"inproc://stg-bag-recorder-{id(self)}-{next(_ids)}"
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._stats = RecorderStats()
        self._overflow = 0
        self._stopped = False

    # -- life cycle -------------------------------------------------------------------------------

    def start(self, timeout: float = 10.0) -> Recorder:
        """Subscribe to the whole bus, then open the file; returns once both are done. Nothing is
        written when the bus cannot be reached (e.g. bad CURVE keys): no empty file is left behind."""
        if self._thread is not None:
            raise RuntimeError("Recorder.start() called twice")
        if self._context is None:
            self._context = zmq.Context()
        self._thread = threading.Thread(target=self._read, name="stg-bag-reader", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout):
            self.stop()
            raise RecordingError(f"recorder could not subscribe to {self.config.url} within {timeout} s")
        if self._error is not None:
            error = self._error
            self.stop()
            raise RecordingError(f"recorder cannot subscribe to {self.config.url}: {error}") from error
        try:
            self._writer = BagWriter(self.path, **self._writer_options)
        except BaseException:
            self.stop()
            raise
        log.info("recording %s to %s", self.config.url, self._writer.files[-1])
        return self

    @property
    def subscriber(self) -> Subscriber | None:
        """The whole-bus subscriber (for a node's heartbeat: its traffic and drops)."""
        return self._subscriber

    def stats(self) -> RecorderStats:
        s = self._stats
        sub = self._subscriber
        drops = dict(sub.traffic.drops) if sub is not None else {}
        if self._overflow:
            drops[OVERFLOW] = self._overflow
        with self._cond:
            queued, queued_bytes = len(self._queue), self._queued_bytes
        files = [str(p) for p in self._writer.files] if self._writer is not None else []
        return RecorderStats(
            received=s.received,
            written=s.written,
            bytes_written=s.bytes_written,
            filtered=s.filtered,
            queued=queued,
            queued_bytes=queued_bytes,
            drops={k: v for k, v in drops.items() if v},
            duplicates=sub.traffic.duplicates if sub is not None else 0,
            files=files,
        )

    def _end_info(self) -> dict[str, str]:
        """What each finished file records about the session so far (format.META_END)."""
        stats = self.stats()
        return {
            "drops": json.dumps(stats.drops, sort_keys=True),
            "received": str(stats.received),
            "duplicates": str(stats.duplicates),
        }

    def stop(self) -> RecorderStats:
        """Stop receiving (what has already reached this process is kept), write what is queued,
        finish the file(s). Idempotent."""
        if self._stopped:
            return self.stats()
        self._stopped = True
        self._stop.set()
        if self._thread is not None and self._ready.is_set() and self._error is None:
            waker = self._context.socket(zmq.PAIR)
            waker.linger = 0
            try:
                waker.connect(self._wake_endpoint)
                waker.send(b"stop", zmq.NOBLOCK)
            except zmq.ZMQError:
                pass  # the thread notices the stop flag within _POLL_MS anyway
            finally:
                waker.close(linger=0)
        if self._thread is not None:
            self._thread.join(timeout=10.0)
            if self._thread.is_alive():
                log.error("recorder reader thread did not stop")
        try:
            if self._writer is not None:
                while self._write_queued(deadline=None):
                    pass
        finally:
            stats = self.stats()
            if self._writer is not None:
                self._writer.close()
            if self._own_context and self._context is not None:
                self._context.term()
        return stats

    def __enter__(self) -> Recorder:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # -- the reader thread ----------------------------------------------------------------------

    def _read(self) -> None:
        try:
            sub = Subscriber(self.config, [""], context=self._context, typed=False, keep_last=False)
            wake = self._context.socket(zmq.PAIR)
            wake.linger = 0
            wake.bind(self._wake_endpoint)
        except BaseException as exc:  # reported by start()
            self._error = exc
            self._ready.set()
            return
        self._subscriber = sub
        poller = zmq.Poller()
        for sock in sub.sockets:
            poller.register(sock, zmq.POLLIN)
        poller.register(wake, zmq.POLLIN)
        self._ready.set()
        try:
            while not self._stop.is_set():
                poller.poll(_POLL_MS)  # stop() wakes it at once through the PAIR
                while not self._stop.is_set():
                    env = sub.recv(timeout=0)
                    if env is None:
                        break
                    self._take(env)
            # Stopped: what has already reached this process is part of the session; keep it (up
            # to _DRAIN_S, until nothing has come for _QUIET_S: some may still be on its way in).
            deadline = time.monotonic() + _DRAIN_S
            while (left := deadline - time.monotonic()) > 0:
                env = sub.recv(timeout=min(_QUIET_S, left))
                if env is None:
                    break
                self._take(env)
        except Exception as exc:
            self._error = exc
            log.exception("recorder reader thread failed")
        finally:
            sub.close()
            wake.close(linger=0)
            with self._cond:
                self._cond.notify_all()

    def _take(self, env) -> None:
        """Queue one received message for writing (or count it filtered out, or overflowing)."""
        received_ns = time.time_ns()
        if self._match is not None and not self._match(env.topic):
            self._stats.filtered += 1
            return
        self._stats.received += 1
        size = env.nbytes
        with self._cond:
            if self._queue and self._queued_bytes + size > self.max_queue_bytes:
                self._overflow += 1
                return
            self._queue.append((received_ns, env))
            self._queued_bytes += size
            self._cond.notify()

    # -- writing (the caller's thread) ------------------------------------------------------------

    def _write_queued(self, deadline: float | None) -> int:
        written = 0
        writer = self._writer
        while deadline is None or time.monotonic() < deadline:
            with self._cond:
                if not self._queue:
                    break
                received_ns, env = self._queue.popleft()
                self._queued_bytes -= env.nbytes
            writer.write(env, received_ns)
            written += 1
            self._stats.written += 1
            self._stats.bytes_written += env.nbytes
        return written

    def poll(self, timeout: float = 0.1) -> int:
        """Write what has arrived (waiting up to ``timeout`` s for something); returns messages written.

        Raises RecordingError if the reader thread failed or the file cannot be written."""
        if self._writer is None or self._stopped:
            raise RuntimeError("poll() on a recorder that is not running")
        if self._error is not None:
            raise RecordingError(f"recorder stopped receiving: {self._error}") from self._error
        with self._cond:
            if not self._queue and timeout > 0:
                self._cond.wait(timeout)
        try:
            written = self._write_queued(time.monotonic() + _WRITE_SLICE_S)
            self._writer.maybe_flush()
        except OSError as exc:
            raise RecordingError(f"cannot write {self._writer.files[-1]}: {exc}") from exc
        return written
