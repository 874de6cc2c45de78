"""The broker: one XSUB/XPUB proxy per lane, with a last-value cache for latched topics.

Publishers connect to the lanes' ``in`` endpoints (XSUB), subscribers to the ``out``
endpoints (XPUB); the broker forwards messages downstream and subscriptions upstream,
zero-copy (the received zmq frames are sent on as they are). It can bind several bus
URLs at once, e.g. ipc for the nodes on this machine and tcp (with CURVE) for a robot.

Latching: the broker keeps the last message of every latched topic (avatar/snapshot in
any namespace). Its XPUB sockets run in ZMQ_XPUB_MANUAL_LAST_VALUE mode: each
subscription is read, applied by hand, and the next send after it goes to the new
subscriber only. So a late joiner receives the cached model at once and nobody else sees
it twice. When there is nothing to replay, that next send is a one-frame empty message
(a no-op that only whole-bus subscribers, prefix "", can receive; receivers ignore it).

The cache must hold the latest value even when nobody listens: publishers filter on their
side (PUB/SUB sends a message only to peers subscribed to it), so an upstream socket that
only forwarded its subscribers' subscriptions would never see a snapshot published while no
renderer runs, and a renderer started later would get nothing. So the upstream (XSUB)
socket of every lane that carries a latched topic subscribes to everything itself. Those
lanes carry only large, rare messages (bulk: snapshots); the keep-last camera lane is never
pulled that way. A publisher of a latched topic therefore always sees a subscriber (the
broker): what it sends is never lost, and a subscriber whose subscription is still on its
way gets the latest value on arrival, as any late joiner.

The broker publishes its own NodeStatus (src ``broker``) every ``status_period_s`` with
per-topic rates and bandwidth of everything it forwards.
"""

from __future__ import annotations

import logging
import os
import socket as pysocket
import threading
import time

import zmq

from stg_node.bus import security, sockets
from stg_node.bus.codec import decode_envelope, encode
from stg_node.bus.config import BusConfig, default_url
from stg_node.bus.messages import TOPIC_TYPES, NodeStatus
from stg_node.bus.sockets import NOBLOCK, recv_multipart, send_frames
from stg_node.bus.spec import MessageError
from stg_node.bus.stats import DropLog, RateMeter, Traffic
from stg_node.bus.topics import LANES, base_name, join_namespace

log = logging.getLogger(__name__)

LATCHED_TOPICS = frozenset(name for name, cls in TOPIC_TYPES.items() if cls.SPEC.latched)
_BATCH = 256  # messages forwarded per socket before looking at the others again
_MAX_TOPICS_TRACKED = 1024
NOOP = b""
SUBSCRIBE_ALL = b"\x01"  # an XSUB subscription message: 1, then the (empty) prefix


class BrokerRunning(RuntimeError):
    """Another broker already serves this ipc endpoint."""


class Broker:
    """XSUB/XPUB proxy for every lane of every URL in ``urls``; see the module docstring.

    ``keys``: CURVE key directory; tcp endpoints then admit only authorised keys (ipc too
    with ``curve_on_ipc``). ``latched``: the topic names to cache (default: the standard
    latched topics); ``lanes``: lane overrides as in BusConfig (a launch file's ``bus.lanes``),
    so the broker pulls a latched topic moved to another lane on that lane. Use as a context
    manager (runs in a thread) or call :meth:`run` in the main thread (returns on :meth:`stop`
    or Ctrl-C).
    """

    def __init__(
        self,
        urls=None,
        *,
        keys=None,
        curve_on_ipc: bool = False,
        node: str = "broker",
        namespace: str = "",
        status_period_s: float = 1.0,
        latched=None,
        lanes: dict[str, str] | None = None,
        context: zmq.Context | None = None,
    ):
        if isinstance(urls, str):
            urls = [urls]
        self.urls = list(urls or [default_url()])
        self.configs = [
            BusConfig(url=u, keys=keys, curve_on_ipc=curve_on_ipc, lanes=dict(lanes or {})) for u in self.urls
        ]
        self.node = node
        self.status_topic = join_namespace(namespace, "node/status")
        self.status_period_s = status_period_s
        self.latched = frozenset(latched) if latched is not None else LATCHED_TOPICS
        #: lanes whose upstream subscribes to everything, so the cache sees every latched message
        self.latch_lanes = frozenset(self.configs[0].lane_of(name).name for name in self.latched)
        self.traffic = Traffic()
        self.cache: dict[bytes, list] = {}  # latched topic -> last message's frames
        #: (Un)subscriptions applied so far: what shows that a subscriber's arrival or departure
        #: has been dealt with (tests and tools wait for it rather than for a guessed time).
        self.subscription_events = 0
        self._own_context = context is None
        self._context = context or zmq.Context()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lanes: list[tuple[zmq.Socket, zmq.Socket]] = []
        self._status_seq = 0
        self._started = time.monotonic()
        self._drop_log = DropLog(log)
        self._topics: dict[bytes, tuple[str, bool]] = {}
        self._closed = False
        try:
            self._bind()
        except BaseException:
            self._close_sockets()
            raise

    # -- set-up -----------------------------------------------------------------------------

    def _bind(self) -> None:
        for lane in LANES.values():
            xsub = sockets.make_socket(self._context, zmq.XSUB, lane)
            xpub = sockets.make_socket(self._context, zmq.XPUB, lane)
            xpub.setsockopt(zmq.XPUB_MANUAL_LAST_VALUE, 1)
            if lane.name in self.latch_lanes:
                xsub.send(SUBSCRIBE_ALL)  # resent by libzmq to every publisher that connects later
            self._lanes.append((xsub, xpub))
            for config in self.configs:
                for sock, side in ((xsub, "in"), (xpub, "out")):
                    endpoint = config.endpoint(lane, side)
                    if sockets.ipc_in_use(endpoint):
                        raise BrokerRunning(
                            f"a broker already serves {endpoint}; stop it or use another --bus URL"
                        )
                    sockets.bind(sock, endpoint, config)
        self._status_lane = list(LANES).index("reliable")
        log.info(
            "broker up on %s%s",
            ", ".join(self.urls),
            " (CURVE on tcp)" if any(c.keys for c in self.configs) else "",
        )

    # -- running ----------------------------------------------------------------------------

    def start(self) -> Broker:
        """Run in a background thread."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run_guarded, name="stg-broker", daemon=True)
            self._thread.start()
        return self

    def _run_guarded(self) -> None:
        try:
            self._loop()
        except Exception:
            log.exception("broker loop failed")
            raise

    def run(self) -> None:
        """Run in this thread until stop() or Ctrl-C (KeyboardInterrupt ends it cleanly)."""
        try:
            self._loop()
        except KeyboardInterrupt:
            log.info("broker interrupted")
        finally:
            self.close()

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout)
            if self._thread.is_alive():  # never close sockets under a running loop
                log.error("broker thread did not stop within %.1f s; leaving its sockets open", timeout)
                return
        self.close()

    def _loop(self) -> None:
        poller = zmq.Poller()
        role: dict[zmq.Socket, tuple[str, zmq.Socket, zmq.Socket]] = {}
        for xsub, xpub in self._lanes:
            poller.register(xsub, zmq.POLLIN)
            poller.register(xpub, zmq.POLLIN)
            role[xsub] = ("data", xsub, xpub)
            role[xpub] = ("subs", xsub, xpub)
        next_status = time.monotonic()
        rates = RateMeter()
        while not self._stop.is_set():
            now = time.monotonic()
            if self.status_period_s > 0 and now >= next_status:
                self._publish_status(rates)
                next_status = now + self.status_period_s
            wait_ms = 100
            if self.status_period_s > 0:
                wait_ms = max(0, min(wait_ms, int((next_status - now) * 1000) + 1))
            for sock, _ in poller.poll(wait_ms):
                kind, xsub, xpub = role[sock]
                if kind == "data":
                    self._forward(xsub, xpub)
                else:
                    self._subscriptions(xsub, xpub)

    def _forward(self, xsub: zmq.Socket, xpub: zmq.Socket) -> None:
        """Move up to a batch of messages downstream, zero-copy (the frames are re-sent as is)."""
        for _ in range(_BATCH):
            try:
                frames = recv_multipart(xsub, NOBLOCK)
            except zmq.Again:
                return
            topic = frames[0].bytes
            info = self._topics.get(topic)
            if info is None:
                info = self._topic_info(topic)
            name, latched = info
            self.traffic.count(name, sum(map(len, frames)) - len(topic))
            if latched:
                self._latch(topic, frames)
            send_frames(xpub, frames)

    def _topic_info(self, topic: bytes) -> tuple[str, bool]:
        """Stats name and whether latched, per topic; bounded against peers inventing topics."""
        name = topic.decode("utf-8", "replace")
        latched = bool(self.latched) and base_name(name, self.latched) is not None
        if len(self._topics) >= _MAX_TOPICS_TRACKED:
            return "<other>", latched
        info = self._topics[topic] = (name, latched)
        return info

    def _latch(self, topic: bytes, frames: list) -> None:
        """Cache a latched topic's message, once its envelope has been checked."""
        try:
            decode_envelope(frames)
        except MessageError as exc:
            self.traffic.drop(exc.reason)
            self._drop_log(topic.decode("utf-8", "replace"), exc.reason, f"not latched: {exc}")
            return
        self.cache[topic] = frames

    def _subscriptions(self, xsub: zmq.Socket, xpub: zmq.Socket) -> None:
        while xpub.get(zmq.EVENTS) & zmq.POLLIN:
            event = xpub.recv()
            replay: list = []
            if event and event[0] in (0, 1):
                prefix = event[1:]
                if event[0] == 1:
                    xpub.setsockopt(zmq.SUBSCRIBE, prefix)
                    replay = [frames for topic, frames in self.cache.items() if topic.startswith(prefix)]
                else:
                    xpub.setsockopt(zmq.UNSUBSCRIBE, prefix)
                xsub.send(event)
                self.subscription_events += 1
            # The first send after reading a (un)subscription goes to that subscriber only.
            if replay:
                for frames in replay:  # beyond the first, these reach every matching subscriber
                    xpub.send_multipart(frames, copy=False)
            else:
                xpub.send(NOOP)

    def _publish_status(self, rates: RateMeter) -> None:
        now = time.monotonic()
        msgs = dict(self.traffic.messages)
        interval = rates.sample(msgs, self.traffic.bytes)
        status = NodeStatus(
            node=self.node,
            state="running",
            pid=os.getpid(),
            host=pysocket.gethostname(),
            uptime_s=now - self._started,
            period_s=self.status_period_s,
            received=msgs,
            rates_hz=interval.rates_hz,
            bytes_per_s=interval.bytes_per_s,
            drops=dict(self.traffic.drops),
            errors=self.traffic.errors,
            last_error=self.traffic.last_error,
        )
        try:
            frames = encode(
                status, topic=self.status_topic, seq=self._status_seq, src=self.node, stamp_ns=time.time_ns()
            )
        except MessageError as exc:  # e.g. too many topics for one header
            self.traffic.error(f"status not published: {exc}")
            return
        self._lanes[self._status_lane][1].send_multipart(frames, copy=False)
        self._status_seq += 1

    # -- shutdown ---------------------------------------------------------------------------

    def _close_sockets(self) -> None:
        for xsub, xpub in self._lanes:
            xsub.close(linger=0)
            xpub.close(linger=0)
        self._lanes = []
        self.cache.clear()
        security.stop_authenticator(self._context)
        if self._own_context:
            self._context.term()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        self._close_sockets()
        for config in self.configs:  # leave no stale ipc socket files behind
            for lane in LANES.values():
                for side in ("in", "out"):
                    path = sockets.ipc_path(config.endpoint(lane, side))
                    if path is not None:
                        path.unlink(missing_ok=True)
        log.info("broker stopped")

    def __enter__(self) -> Broker:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
