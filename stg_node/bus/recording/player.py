"""Player: a recording back onto the bus, byte for byte, in its original timing or in lockstep.

    player = Player(BagReader("session.mcap"), config=BusConfig.from_env(), rate=1.0)
    stats = player.run()                       # blocks; player.stop() from another thread ends it

Each recorded message is sent as the exact bytes that were recorded (``Publisher.forward``:
same topic, header, seq, stamp and src), on its topic's lane.

Timing: message i goes out at ``start + (log_time_i - log_time_0) / rate`` (the receive
times the recorder saw, so the original pacing); ``rate=0`` sends as fast as possible. On
the keep-last lane (camera/frame, avatar/image) a fast sender loses messages by design
(4-deep queues); use lockstep to deliver every one.

Lockstep (:class:`Lockstep`): after sending a message whose topic needs it, the player
waits until ``acks`` acknowledgements arrived on the ack topic (default ``node/ack``)
before the next. An :class:`~stg_node.bus.Ack` counts when it names the message sent
(topic, seq, src); any other message on the ack topic counts as one acknowledgement, so a
consumer's own output can serve (``ack_topic="trainer/metrics"``: one training step per
frame). A missing acknowledgement fails after ``timeout_s``: a regression run never
hangs. Before the first message, it waits for a subscriber of every topic it will play.

A recorded message that is not a valid bus message (a damaged or foreign file) is skipped,
logged and counted in :attr:`PlayStats.skipped`; playback goes on.

Pause: :meth:`pause`, :meth:`resume`, :meth:`step` (one message while paused); ``paused=True``
starts paused. Pauses do not count as recording time.
"""

from __future__ import annotations

import logging
import re
import threading
import time
from dataclasses import dataclass, field

import zmq

from stg_node.bus import BusConfig, Publisher, Subscriber
from stg_node.bus.config import as_config
from stg_node.bus.recording.format import RecordingError
from stg_node.bus.recording.reader import BagReader
from stg_node.signals import StopEvent

log = logging.getLogger(__name__)

DEFAULT_ACK_TOPIC = "node/ack"
_TICK_S = 0.05  # longest uninterrupted sleep: stop/pause/step react within this


class PlaybackError(RuntimeError):
    """Playback could not go on (an empty recording, no subscriber or no acknowledgement in lockstep)."""


@dataclass
class Lockstep:
    """Wait for consumers: ``acks`` acknowledgements on ``ack_topic`` per message whose topic
    matches ``topics`` (a regex; None: every message played), each within ``timeout_s``."""

    ack_topic: str = DEFAULT_ACK_TOPIC
    acks: int = 1
    timeout_s: float = 30.0
    topics: str | None = None

    def __post_init__(self):
        if self.acks < 1:
            raise ValueError(f"lockstep needs at least 1 acknowledgement per message, got {self.acks}")
        if self.timeout_s <= 0:
            raise ValueError(f"lockstep timeout must be > 0 s, got {self.timeout_s}")


@dataclass
class PlayStats:
    published: int = 0
    bytes: int = 0
    loops: int = 0
    acks: int = 0
    stray_acks: int = 0  # Acks naming another message than the one awaited (ignored)
    skipped: int = 0  # recorded messages that are not valid bus messages (logged, not sent)
    topics: dict[str, int] = field(default_factory=dict)


class Player:
    """Plays ``reader`` onto the bus; see the module docstring."""

    def __init__(
        self,
        reader: BagReader,
        *,
        config: BusConfig | str | None = None,
        rate: float = 1.0,
        loop: bool = False,
        topics=None,
        start_offset_s: float = 0.0,
        paused: bool = False,
        lockstep: Lockstep | None = None,
        wait_for_subscribers_s: float = 1.0,
        drain_s: float = 0.5,
        context: zmq.Context | None = None,
    ):
        if rate < 0:
            raise ValueError(f"rate must be >= 0 (0 = as fast as possible), got {rate}")
        if start_offset_s < 0:
            raise ValueError(f"start offset must be >= 0 s, got {start_offset_s}")
        self.config = config = as_config(config)
        self.reader = reader
        self.rate = rate
        self.loop = loop
        self.topics = topics
        self.lockstep = lockstep
        self.wait_for_subscribers_s = wait_for_subscribers_s
        self.drain_s = drain_s
        self.stats = PlayStats()
        first = reader.start_ns
        self.start_ns = None if first is None else first + int(start_offset_s * 1e9)
        self._ack_match = re.compile(lockstep.topics) if lockstep and lockstep.topics else None
        self._context = context
        # set from signal handlers (stg-bag play: Ctrl-C, SIGUSR1, SIGUSR2) in the thread that
        # waits on them: re-entrant locks (stg_node.signals explains the deadlock otherwise)
        self._stop = StopEvent()
        self._running = StopEvent()  # set = playing, clear = paused
        self._steps = 0
        self._step_lock = threading.RLock()
        if not paused:
            self._running.set()

    # -- control (any thread) ---------------------------------------------------------------------

    def pause(self) -> None:
        self._running.clear()

    def resume(self) -> None:
        self._running.set()

    def toggle_pause(self) -> bool:
        """Pause or resume; returns True when now paused."""
        if self._running.is_set():
            self.pause()
            return True
        self.resume()
        return False

    @property
    def paused(self) -> bool:
        return not self._running.is_set()

    def step(self) -> None:
        """While paused, let one more message out."""
        with self._step_lock:
            self._steps += 1

    def stop(self) -> None:
        self._stop.set()

    # -- playing ----------------------------------------------------------------------------------

    def _take_step(self) -> bool:
        with self._step_lock:
            if self._steps:
                self._steps -= 1
                return True
        return False

    def _wait_turn(self, due: float | None) -> tuple[bool, float]:
        """Wait until ``due`` (monotonic; None = now) while honouring pause/step/stop.
        Returns (go on, seconds spent paused)."""
        paused_for = 0.0
        while not self._stop.is_set():
            if not self._running.is_set():
                if self._take_step():
                    return True, paused_for
                began = time.monotonic()
                self._running.wait(_TICK_S)
                paused_for += time.monotonic() - began
                if due is not None:
                    due += time.monotonic() - began
                continue
            if due is None:
                return True, paused_for
            left = due - time.monotonic()
            if left <= 0:
                return True, paused_for
            self._stop.wait(min(left, _TICK_S))
        return False, paused_for

    def _wait_for_subscribers(self, pub: Publisher, topics: list[str]) -> None:
        if self.lockstep is not None:
            deadline = time.monotonic() + self.lockstep.timeout_s
            for topic in topics:
                while not pub.has_subscribers("/" + topic):
                    if self._stop.is_set():
                        return
                    if time.monotonic() >= deadline:
                        raise PlaybackError(
                            f"lockstep: nobody subscribes to {topic!r} on {self.config.url} "
                            f"after {self.lockstep.timeout_s:g} s"
                        )
                    time.sleep(0.01)
            return
        deadline = time.monotonic() + self.wait_for_subscribers_s
        for topic in topics:
            if not pub.wait_for_subscribers("/" + topic, max(0.0, deadline - time.monotonic())):
                log.info("no subscriber for %s yet; playing it anyway", topic)

    def _await_ack(self, acks: Subscriber, env) -> None:
        header = env.header
        wanted = (env.topic, header["seq"], header["src"])
        deadline = time.monotonic() + self.lockstep.timeout_s
        got = 0
        while got < self.lockstep.acks:
            if self._stop.is_set():
                return
            left = deadline - time.monotonic()
            if left <= 0:
                raise PlaybackError(
                    f"lockstep: {got} of {self.lockstep.acks} acknowledgement(s) on "
                    f"{acks.topics[0]!r} within {self.lockstep.timeout_s:g} s for {env.topic} "
                    f"seq {header['seq']} from {header['src']} (message {self.stats.published})"
                )
            ack = acks.recv(timeout=min(left, _TICK_S))
            if ack is None:
                continue
            h = ack.header
            if h["type"] == "Ack":
                if (h.get("msg_topic"), h.get("msg_seq"), h.get("msg_src")) != wanted:
                    self.stats.stray_acks += 1
                    continue
            got += 1
            self.stats.acks += 1

    def run(self) -> PlayStats:
        """Play until the end (every loop, with ``loop``) or :meth:`stop`; returns what was sent."""
        if self.start_ns is None:
            raise PlaybackError("the recording holds no messages")
        topics = self.reader.topics(self.topics)
        if not topics:
            raise PlaybackError(f"no recorded topic matches {self.topics!r}")
        own_context = self._context is None
        context = self._context or zmq.Context()
        acks = None
        try:
            with Publisher(self.config, node="stg-bag-play", context=context) as pub:
                if self.lockstep is not None:
                    acks = Subscriber(
                        self.config, [self.lockstep.ack_topic], context=context, typed=False, keep_last=False
                    )
                    pub.wait_for_subscribers(
                        self.lockstep.ack_topic, timeout=min(2.0, self.lockstep.timeout_s)
                    )
                self._wait_for_subscribers(pub, topics)
                while not self._stop.is_set():
                    self._play_once(pub, acks)
                    self.stats.loops += 1
                    if not self.loop:
                        break
                if self.drain_s > 0 and not self._stop.is_set():
                    time.sleep(self.drain_s)  # LINGER 0: give queued messages time to leave
        finally:
            if acks is not None:
                acks.close()
            if own_context:
                context.term()
        return self.stats

    def _play_once(self, pub: Publisher, acks: Subscriber | None) -> None:
        origin_log: int | None = None
        origin_wall = 0.0
        for msg in self.reader.messages(self.topics, start_ns=self.start_ns):
            if origin_log is None:
                origin_log, origin_wall = msg.log_time_ns, time.monotonic()
            due = None if self.rate == 0 else origin_wall + (msg.log_time_ns - origin_log) / 1e9 / self.rate
            go, paused_for = self._wait_turn(due)
            if not go:
                return
            origin_wall += paused_for
            try:
                env = pub.forward(msg.frames())
            except (ValueError, RecordingError) as exc:  # a damaged or foreign message: skip it, say so
                self.stats.skipped += 1
                log.warning("skipped recorded message at %d ns on %s: %s", msg.log_time_ns, msg.topic, exc)
                continue
            self.stats.published += 1
            self.stats.bytes += env.nbytes
            self.stats.topics[env.topic] = self.stats.topics.get(env.topic, 0) + 1
            if acks is not None and (self._ack_match is None or self._ack_match.search(env.topic)):
                self._await_ack(acks, env)
