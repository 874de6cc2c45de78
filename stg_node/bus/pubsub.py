"""Publisher and Subscriber: typed messages over the bus's lanes, zero-copy both ways.

    with Publisher(config, node="tracker") as pub:
        pub.publish(BodyPose(poses=..., Rh=..., Th=..., betas=...))

    with Subscriber(config, ["camera/frame"]) as sub:
        for frame in sub.messages(timeout=5.0):     # stops after 5 s without a message
            ...

A Publisher opens one XPUB socket per lane (so it can see subscriptions:
:meth:`Publisher.wait_for_subscribers`), numbers messages per topic (``seq``) and sends
``[topic, header, *arrays]`` with ``copy=False``: the arrays' memory goes to ZeroMQ as
is, so do not modify an array until the message has left (publish a fresh array per
message, as camera drivers naturally do).

On lanes with short queues (keep-last, bulk) the Publisher reads its socket's EVENTS before
each send: that makes libzmq apply the read acknowledgements the receiving side has sent (it
otherwise applies them only now and then), so a queue the reader has in fact drained is never
taken for full and the newest message dropped in its place. Without it, two frames sent back
to back to a subscriber that keeps up could lose the second one.

A Subscriber opens one SUB socket per lane its topics live on. On keep-last lanes a small
thread drains the socket continuously and keeps only the newest message per topic
(channels.LatestChannel explains why a thread). It
checks every message (codec.decode) and tracks sequence numbers per (topic, src):
malformed messages, gaps and skips are counted in :attr:`Subscriber.traffic` (published
in NodeStatus by the heartbeat), logged once per source per 10 s, and never raised.
"""

from __future__ import annotations

import itertools
import logging
import os
import sys
import threading
import time
from collections import deque

import msgpack
import zmq

from stg_node.bus import sockets
from stg_node.bus.channels import DirectChannel, LatestChannel
from stg_node.bus.codec import Envelope, decode, decode_envelope, encode_counted
from stg_node.bus.config import BusConfig, as_config
from stg_node.bus.messages import Message
from stg_node.bus.sockets import EVENTS, POLLIN, send_frames
from stg_node.bus.spec import MAX_HEADER_BYTES, MessageError
from stg_node.bus.stats import DropLog, SeqTracker, Traffic
from stg_node.bus.topics import LANES, Lane

log = logging.getLogger(__name__)

WILDCARDS = ("", "*", "#")
#: Lanes with a high-water mark up to this apply read acknowledgements before each send.
SHORT_QUEUE = 64
_as_config = as_config  # its former private home; config.as_config is the one to import


def default_node_id() -> str:
    prog = os.path.basename(sys.argv[0] or "python").removesuffix(".py") or "python"
    return f"{prog}-{os.getpid()}"


def _timeout_ms(deadline: float | None) -> int:
    if deadline is None:
        return -1
    return max(0, int((deadline - time.monotonic()) * 1000 + 0.999))


class Publisher:
    """Publishes typed messages; one XPUB socket per lane. Thread-safe (a lock serialises use).

    ``bind=False`` (default) connects to a broker's ``in`` endpoints; ``bind=True`` binds
    the ``out`` endpoints itself, for a bus without a broker. ``lanes`` limits the sockets
    opened (default: all lanes).
    """

    def __init__(
        self,
        config: BusConfig | str | None = None,
        *,
        node: str | None = None,
        context: zmq.Context | None = None,
        bind: bool = False,
        lanes=None,
    ):
        self.config = as_config(config)
        self.node = node or default_node_id()
        self.traffic = Traffic()
        self._context = context or zmq.Context.instance()
        self._sockets: dict[str, zmq.Socket] = {}
        self._routes: dict[tuple[str, type], tuple[str, bytes, zmq.Socket]] = {}
        self._seq: dict[str, int] = {}
        self._subscriptions: dict[zmq.Socket, dict[bytes, int]] = {}  # per lane socket
        self._short_queues: set[zmq.Socket] = set()  # lanes whose sends first apply read acks
        self._closed = False
        self._lock = threading.Lock()
        self._published = 0
        try:
            for name in lanes or LANES:
                lane = LANES[name]
                sock = sockets.make_socket(self._context, zmq.XPUB, lane)
                self._sockets[lane.name] = sock
                if lane.hwm <= SHORT_QUEUE:
                    self._short_queues.add(sock)
                if bind:
                    sockets.bind(sock, self.config.endpoint(lane, "out"), self.config)
                else:
                    sockets.connect(sock, self.config.endpoint(lane, "in"), self.config)
        except BaseException:
            self.close()
            raise

    # -- publishing ------------------------------------------------------------------------

    def _route(self, name: str, cls: type) -> tuple[str, bytes, zmq.Socket]:
        topic = self.config.topic(name)
        want = self.config.expected_type(topic)
        if want is not None and want is not cls:
            raise ValueError(
                f"{cls.__name__} cannot be published on {topic!r}, which carries {want.__name__}"
            )
        lane = self.config.lane_of(topic)
        sock = self._sockets.get(lane.name)
        if sock is None:
            raise ValueError(
                f"topic {topic!r} travels on lane {lane.name!r}, which this publisher did not open"
            )
        route = (topic, topic.encode(), sock)
        self._routes[(name, cls)] = route
        return route

    def publish(self, msg: Message, topic: str | None = None, *, stamp_ns: int | None = None) -> int:
        """Send ``msg`` on ``topic`` (default: its standard topic, in the namespace); returns its seq.

        ``stamp_ns`` (else ``msg.header.stamp_ns``, else now) is the time the data refers to.
        Raises MessageError (a ValueError) if the message breaks its schema.
        """
        name = topic if topic is not None else msg.SPEC.topic
        with self._lock:
            if self._closed:
                raise RuntimeError("publish() on a closed Publisher")
            route = self._routes.get((name, type(msg))) or self._route(name, type(msg))
            full, _, sock = route
            seq = self._seq.get(full, 0)
            stamp = stamp_ns or msg.header.stamp_ns or time.time_ns()
            frames, nbytes = encode_counted(msg, topic=full, seq=seq, src=self.node, stamp_ns=stamp)
            if sock in self._short_queues:
                sock.get(EVENTS)  # apply pending read acknowledgements (module docstring)
            send_frames(sock, frames)
            self._seq[full] = seq + 1
            self.traffic.count(full, nbytes)
            self._published += 1
            if not self._published % 256:  # keep the XPUB's subscription queue short
                self._read_subscriptions(sock)
        return seq

    def forward(self, frames) -> Envelope:
        """Send an already encoded message ``[topic, header, *buffers]`` exactly as it is (a
        recording played back, a bridge): same topic, seq, stamp and src. Its envelope is checked
        first (MessageError when broken) and so is its type against a standard topic; returns it."""
        env = decode_envelope(frames)
        want = self.config.expected_type(env.topic)
        if want is not None and want.SPEC.type != env.type:
            raise MessageError(
                "type_mismatch", f"{env.type} on topic {env.topic!r}, which carries {want.SPEC.type}"
            )
        with self._lock:
            if self._closed:
                raise RuntimeError("forward() on a closed Publisher")
            lane = self.config.lane_of(env.topic)
            sock = self._sockets.get(lane.name)
            if sock is None:
                raise ValueError(
                    f"topic {env.topic!r} travels on lane {lane.name!r}, which this publisher did not open"
                )
            if sock in self._short_queues:
                sock.get(EVENTS)
            send_frames(sock, frames)
            self.traffic.count(env.topic, env.nbytes)
            self._published += 1
            if not self._published % 256:
                self._read_subscriptions(sock)
        return env

    # -- subscriptions seen (XPUB) ------------------------------------------------------------

    def _read_subscriptions(self, sock: zmq.Socket) -> None:
        seen = self._subscriptions.setdefault(sock, {})
        while sock.get(EVENTS) & POLLIN:
            event = sock.recv()
            if not event:
                continue
            prefix = event[1:]
            if event[0] == 1:
                seen[prefix] = seen.get(prefix, 0) + 1
            elif event[0] == 0 and prefix in seen:
                seen[prefix] -= 1
                if seen[prefix] <= 0:
                    del seen[prefix]

    def has_subscribers(self, topic: str | None = None) -> bool:
        """Whether a subscription matching ``topic`` has reached this publisher on the lane the
        topic travels on (with None: any subscription on any lane)."""
        with self._lock:
            for sock in self._sockets.values():
                self._read_subscriptions(sock)
        if topic is None:
            return any(self._subscriptions.values())
        full = self.config.topic(topic)
        sock = self._sockets.get(self.config.lane_of(full).name)
        raw = full.encode()
        return any(raw.startswith(prefix) for prefix in self._subscriptions.get(sock, ()))

    def wait_for_subscribers(self, topic: str | None = None, timeout: float = 5.0) -> bool:
        """Block until a subscription matching ``topic`` arrives (True) or ``timeout`` s pass (False).

        Avoids ZeroMQ's slow-joiner loss: messages sent before any subscription reached the
        publisher are discarded by PUB/SUB by design.
        """
        deadline = time.monotonic() + timeout
        while not self.has_subscribers(topic):
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.005)  # not zmq.poll: the sockets may be in use by another thread
        return True

    # -- life cycle ---------------------------------------------------------------------------

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            for sock in self._sockets.values():
                sock.close(linger=0)

    def __enter__(self) -> Publisher:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Subscriber:
    """Receives messages on a set of topics, checked, typed and counted.

    ``topics``: names relative to the namespace (``camera/frame``), absolute names
    (``/rig2/camera/frame``), message classes (their standard topic), prefixes ending in
    '/' (``rig1/``) or a wildcard (``""``, ``"*"``: everything, on all lanes).
    ``typed=False`` yields :class:`Envelope` (any type, checked at envelope level) instead
    of typed messages. ``keep_last`` overrides the lanes' policy: None follows the lane
    (keep-last on ``latest``), False delivers every message in order, True keeps only the
    newest message per topic on every lane.
    """

    def __init__(
        self,
        config: BusConfig | str | None = None,
        topics=(),
        *,
        context: zmq.Context | None = None,
        typed: bool = True,
        keep_last: bool | None = None,
        drop_log_interval_s: float = 10.0,
    ):
        self.config = as_config(config)
        self.traffic = Traffic()
        self.typed = typed
        self._context = context or zmq.Context.instance()
        self._keep_last_override = keep_last
        self._channels: dict[str, DirectChannel | LatestChannel] = {}
        self._channel_list: list = []
        self._exact: set[bytes] = set()
        self._prefixes: list[bytes] = []
        self._ready: deque = deque()
        self._rotation = itertools.count()
        self._poller = zmq.Poller()
        self._seq = SeqTracker()
        self._drop_log = DropLog(log, interval_s=drop_log_interval_s)
        self._closed = False
        if isinstance(topics, (str, type)):
            topics = [topics]
        try:
            self.subscribe(*topics)
        except BaseException:
            self.close()
            raise

    # -- subscriptions ------------------------------------------------------------------------

    def _channel(self, lane: Lane):
        channel = self._channels.get(lane.name)
        if channel is None:
            sock = sockets.make_socket(self._context, zmq.SUB, lane)
            try:
                sockets.connect(sock, self.config.endpoint(lane, "out"), self.config)
            except BaseException:
                sock.close(linger=0)
                raise
            keep_last = lane.keep_last if self._keep_last_override is None else self._keep_last_override
            if keep_last:
                channel = LatestChannel(self._context, sock, lane)
            else:
                channel = DirectChannel(sock, lane)
            self._channels[lane.name] = channel
            self._channel_list.append(channel)
            self._poller.register(channel.pollable, zmq.POLLIN)
        return channel

    def subscribe(self, *topics) -> None:
        """Add topics (same forms as the constructor's)."""
        for topic in topics:
            if isinstance(topic, type) and issubclass(topic, Message):
                topic = topic.SPEC.topic
            if topic in WILDCARDS or topic.endswith("/"):
                prefix = "" if topic in WILDCARDS else self.config.topic(topic[:-1]) + "/"
                raw = prefix.encode()
                self._prefixes.append(raw)
                for lane in LANES.values():
                    self._channel(lane).subscribe(raw)
                continue
            full = self.config.topic(topic)
            raw = full.encode()
            self._exact.add(raw)
            self._channel(self.config.lane_of(full)).subscribe(raw)

    @property
    def topics(self) -> list[str]:
        return sorted(t.decode() for t in self._exact) + [p.decode() + "*" for p in self._prefixes]

    @property
    def sockets(self) -> list[zmq.Socket]:
        """Sockets to register in a node's own zmq.Poller: POLLIN on any means call recv()."""
        return [channel.pollable for channel in self._channel_list]

    # -- receiving ------------------------------------------------------------------------------

    def _next(self, deadline: float | None):
        channels = self._channel_list
        if not channels:
            raise RuntimeError("this subscriber has no topics: call subscribe() first")
        count = len(channels)
        while True:
            if self._ready:
                return self._ready.popleft()
            start = next(self._rotation) if count > 1 else 0
            for i in range(count):
                channel = channels[(start + i) % count]
                items = channel.take()
                if items:
                    lane = channel.lane
                    self._ready.extend((lane, frames) for frames in items)
                    break
            else:
                ms = _timeout_ms(deadline)
                if ms == 0 or not self._poller.poll(ms):
                    return None

    def poll(self, timeout: float | None = None) -> bool:
        """Wait up to ``timeout`` s (None: forever) until something is ready to read.

        True does not promise a valid message: recv() may still drop what arrived."""
        if self._ready:
            return True
        deadline = None if timeout is None else time.monotonic() + timeout
        item = self._next(deadline)
        if item is None:
            return False
        self._ready.appendleft(item)
        return True

    def recv(self, timeout: float | None = None) -> Message | Envelope | None:
        """The next valid message, or None when ``timeout`` s pass without one (None: wait forever)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            item = self._next(deadline)
            if item is None:
                return None
            msg = self._accept(*item)
            if msg is not None:
                return msg

    def messages(self, timeout: float | None = None, count: int | None = None):
        """Iterate over messages; stops after ``timeout`` s without one, or after ``count``."""
        delivered = 0
        while count is None or delivered < count:
            msg = self.recv(timeout)
            if msg is None:
                return
            delivered += 1
            yield msg

    def __iter__(self):
        return self.messages()

    def _accept(self, lane: Lane, frames: list):
        if len(frames) == 1 and len(frames[0]) == 0:
            return None  # broker no-op (see proto/envelope.yaml)
        topic = frames[0].bytes
        if topic not in self._exact and not any(topic.startswith(p) for p in self._prefixes):
            return None  # ZeroMQ filters by prefix; we deliver exact topics only
        try:
            if self.typed:
                msg = decode(frames)
                head = msg.header
                src, seq, name = head.src, head.seq, head.topic
            else:
                msg = decode_envelope(frames)
                src, seq, name = msg.header["src"], msg.header["seq"], msg.topic
        except MessageError as exc:
            self.traffic.drop(exc.reason)
            self._drop_log(_source_of(frames), exc.reason, str(exc))
            return None
        except Exception as exc:  # a decoder bug must not take the node down either
            self.traffic.drop("malformed")
            self.traffic.error(f"decoder failed: {exc!r}")
            self._drop_log(_source_of(frames), "malformed", f"decoder failed: {exc!r}")
            return None
        status, missing = self._seq.check(name, src, seq)
        if status == "duplicate":
            self.traffic.duplicates += 1
            return None
        if status == "gap":
            if self._channels[lane.name].keep_last:
                self.traffic.drop("superseded", missing)
            else:
                self.traffic.drop("lost", missing)
                self._drop_log(
                    f"{src}@{name}", "lost", f"{missing} message(s) lost before seq {seq} on {name}"
                )
        elif status == "restart":
            self.traffic.restarts += 1
        self.traffic.count(name, sum(map(len, frames)) - len(frames[0]))
        return msg

    # -- life cycle -------------------------------------------------------------------------------

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for channel in self._channel_list:
            channel.close()
        self._ready.clear()

    def __enter__(self) -> Subscriber:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _source_of(frames) -> str:
    """Best-effort 'src@topic' of a message that failed to decode, for the drop log."""
    try:
        topic = frames[0].bytes.decode("utf-8", "replace")[:80]
    except Exception:
        topic = "?"
    src = "?"
    if len(frames) >= 2 and len(frames[1]) <= MAX_HEADER_BYTES:
        try:
            header = msgpack.unpackb(memoryview(frames[1]), raw=False)
            if isinstance(header, dict) and isinstance(header.get("src"), str):
                src = header["src"][:80]
        except Exception:
            pass
    return f"{src}@{topic}"
