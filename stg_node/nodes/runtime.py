"""The node runtime: what every node process shares, so a node itself is a few plain lines.

A node is a :class:`Node` subclass with typed parameters (a dataclass, :mod:`.params`) and
either hooks or a loop of its own:

    class Echo(Node):
        kind = "echo"
        Params = EchoParams

        def setup(self):
            self.subscribe("camera/frame")

        def on_message(self, topic, msg):          # or override run(): for event in self.events(): ...
            self.publish(BodyPose(...))

The runtime owns the rest: the bus connection (stg_node.bus.Bus, with remaps and namespace),
a NodeStatus heartbeat on ``node/status`` (node name, pid, host, state, per-topic message
rates, drops, errors) that starts once :meth:`Node.setup` returns (a launcher reads the first
heartbeat as "ready"), log lines carrying the node's name, SIGINT/SIGTERM handlers installed
explicitly (the first asks for a graceful stop, a second aborts), and a shutdown that always
runs :meth:`Node.teardown` (flush what the node owes: a checkpoint, a video) before the bus
closes. :func:`run_node` is the process entry (``python -m stg_node.nodes KIND``); exit code
0 for a clean stop (also by signal), 1 when the node failed.

Lockstep acknowledgements (``ack``: topic names, as the node subscribes them, or ``*``): the
node publishes an :class:`~stg_node.bus.Ack` on ``node/ack`` naming each message it has
finished with on those topics, so ``stg-bag play --lockstep`` sends the next message only
then. Nodes on the hooks get it after :meth:`Node.on_message` returns; a node with its own
loop calls :meth:`Node.acknowledge` where it has finished with a message (the trainer after
the steps a frame is owed, the renderer after the image a request asked for).
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import ClassVar

import zmq

from stg_node.bus import Ack, Bus, BusConfig, Envelope, Heartbeat, Message, Subscriber
from stg_node.nodes.params import NoParams
from stg_node.signals import StopSignals

#: Set by stg-launch: the launcher's pid. A node whose parent changes (the launcher died) stops.
ENV_PARENT_PID = "STG_LAUNCH_PID"
#: Set by stg-launch: how many times this node has been respawned in this launch (0: first start).
ENV_RESPAWN = "STG_RESPAWN"
#: Set by stg-launch: the launch file that started this node (the recorder stores it).
ENV_LAUNCH_FILE = "STG_LAUNCH_FILE"
#: Set by stg-launch on a standby copy (a node's ``standby: true``): prepare, then wait on stdin
#: for ``go RESPAWNS`` (take over) or end of file (not needed); see stg_node.cli.node.
ENV_STANDBY = "STG_STANDBY"
#: How long the event loop waits at most before looking at the stop flag again.
POLL_S = 0.1
#: In ``ack``: acknowledge messages of every topic the node subscribes.
ACK_ALL = "*"


class NodeError(RuntimeError):
    """A node cannot go on for a reason it can state (bad input, a source that cannot be opened):
    logged as one line, without a traceback; the node exits 1."""


@dataclass(frozen=True)
class Event:
    """One thing that happened to a node: a message arrived, or its tick came due."""

    kind: str  # "message" or "tick"
    topic: str = ""  # the name the node subscribed (before remap and namespace)
    message: Message | None = None


class Node:
    """Base of every node; see the module docstring. Construct through :func:`run_node` or directly
    in tests (``Node(name, params, config)``, then :meth:`execute`)."""

    kind: ClassVar[str] = ""
    Params: ClassVar[type] = NoParams
    #: Period of on_tick in seconds (None: no ticks).
    tick_s: ClassVar[float | None] = None
    #: After a teardown that published (a final snapshot), wait this long before closing the bus:
    #: sockets close with LINGER 0, which would drop what is still on its way out.
    linger_s: ClassVar[float] = 0.5

    def __init__(
        self,
        name: str,
        params=None,
        config: BusConfig | str | None = None,
        *,
        remap: dict[str, str] | None = None,
        heartbeat_s: float = 1.0,
        stop: StopSignals | None = None,
        ack: Iterable[str] = (),
    ):
        self.name = name
        self.params = params if params is not None else self.Params()
        self.remap = dict(remap or {})
        self.log = logging.getLogger(f"stg_node.nodes.{name}")
        self.stop_signals = stop or StopSignals()
        self.exit_code = 0
        self._closing = False
        self._owed = False
        self._subscribers: list[tuple[Subscriber, dict[str, str]]] = []
        self._names: dict[str, str] = {}  # full topic -> the name it was subscribed as
        self.ack_topics = frozenset(ack)
        self.acks_sent = 0
        self._poller = zmq.Poller()
        parent = os.environ.get(ENV_PARENT_PID, "")
        self._parent_pid = int(parent) if parent.isdigit() else None
        self._next_parent_check = 0.0
        respawn = os.environ.get(ENV_RESPAWN, "")
        self.respawned = respawn.isdigit() and int(respawn) > 0
        self.bus = Bus(config, node=name, heartbeat_s=0)
        self.heartbeat: Heartbeat | None = None
        if heartbeat_s > 0:
            self.heartbeat = Heartbeat(self.bus.publisher, period_s=heartbeat_s)
            self.bus.heartbeat = self.heartbeat  # the Bus adds its subscribers and stops it on close

    # -- topics -----------------------------------------------------------------------------------

    def topic(self, name: str) -> str:
        """The topic a name stands for in this node (after the launch file's remaps)."""
        return self.remap.get(name, name)

    def subscribe(self, *topics: str, **options) -> Subscriber:
        """A Subscriber on ``topics`` (remapped); its messages arrive as events named as asked here.
        Options as :class:`stg_node.bus.Subscriber` (``keep_last``, ``typed``)."""
        sub = self.bus.subscribe(*(self.topic(t) for t in topics), **options)
        names = {self.bus.config.topic(self.topic(t)): t for t in topics}
        self._subscribers.append((sub, names))
        self._names.update(names)
        for sock in sub.sockets:
            self._poller.register(sock, zmq.POLLIN)
        return sub

    def publish(self, msg: Message, topic: str | None = None, *, stamp_ns: int | None = None) -> int:
        seq = self.bus.publish(msg, self.topic(topic or msg.SPEC.topic), stamp_ns=stamp_ns)
        self._owed = self._closing
        return seq

    # -- lockstep acknowledgements ------------------------------------------------------------------

    def acks(self, name: str) -> bool:
        """Whether this node acknowledges the messages it takes from topic ``name`` (as subscribed)."""
        return name in self.ack_topics or (ACK_ALL in self.ack_topics and name in self._names.values())

    def acknowledge(self, msg: Message | Envelope, name: str | None = None) -> bool:
        """Say that this node has finished with ``msg`` (an Ack naming its topic, seq and src on
        node/ack) if acknowledgements were asked for its topic; True if one was sent. ``name``:
        the topic as subscribed (default: looked up from the message's full topic)."""
        if not self.ack_topics:
            return False
        if isinstance(msg, Envelope):
            topic, seq, src = msg.topic, int(msg.header.get("seq", -1)), str(msg.header.get("src", ""))
        else:
            topic, seq, src = msg.header.topic, msg.header.seq, msg.header.src
        if not self.acks(name if name is not None else self._names.get(topic, topic)) or seq < 0:
            return False
        self.publish(Ack(msg_topic=topic, msg_seq=seq, msg_src=src))
        self.acks_sent += 1
        return True

    def _check_ack_topics(self) -> None:
        subscribed = set(self._names.values())
        for name in sorted(self.ack_topics - {ACK_ALL} - subscribed):
            self.log.warning(
                "ack: this node does not subscribe %r (it subscribes %s); nothing on it will be acknowledged",
                name,
                ", ".join(sorted(subscribed)) or "nothing",
            )
        if self.ack_topics:
            self.log.info("acknowledging %s on node/ack (lockstep)", ", ".join(sorted(self.ack_topics)))

    # -- state --------------------------------------------------------------------------------------

    @property
    def stopping(self) -> bool:
        return self.stop_signals.requested

    def stop(self, reason: str = "requested") -> None:
        """End the node's loop after the current event (teardown still runs)."""
        self.stop_signals.request(reason)

    def fail(self, text: str) -> None:
        """The node cannot go on: log, record the error in its status, stop with exit code 1."""
        self.log.error("%s", text)
        self.exit_code = 1
        self.error(text)
        self.set_state("error")
        self.stop("failed")

    def set_state(self, state: str) -> None:
        if self.heartbeat is not None:
            self.heartbeat.state = state

    def error(self, text: str) -> None:
        """Count a node-level error (shows in NodeStatus.errors / last_error)."""
        if self.heartbeat is not None:
            self.heartbeat.error(text)

    def drop(self, reason: str, count: int = 1) -> None:
        """Count messages this node dropped on purpose (NodeStatus.drops[reason])."""
        if self.heartbeat is not None:
            self.heartbeat.traffic.drop(reason, count)

    def wait_for_messages(self, timeout: float) -> bool:
        """Block until a subscription has something (True), ``timeout`` s pass or a stop comes."""
        if not self._subscribers:
            self.stop_signals.event.wait(timeout)
            return False
        deadline = time.monotonic() + timeout
        while not self.stopping:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            if self._poller.poll(int(min(POLL_S, remaining) * 1000) + 1):
                return True
        return False

    def sleep(self, seconds: float) -> bool:
        """Wait ``seconds`` unless a stop comes first; True if the full time passed."""
        return not self.stop_signals.event.wait(max(0.0, seconds))

    def _check_parent(self) -> None:
        if self._parent_pid is None:
            return
        now = time.monotonic()
        if now < self._next_parent_check:
            return
        self._next_parent_check = now + 1.0
        if os.getppid() != self._parent_pid:
            self.log.warning("launcher (pid %d) is gone: stopping", self._parent_pid)
            self.stop("launcher gone")

    # -- the event loop -------------------------------------------------------------------------------

    def events(self, tick_s: float | None = None) -> Iterator[Event]:
        """Messages on every subscription (one per subscription in turn, so none starves) and a
        tick every ``tick_s`` s; ends when the node is asked to stop."""
        next_tick = time.monotonic() + tick_s if tick_s else None
        while not self.stopping:
            self._check_parent()
            if next_tick is not None and time.monotonic() >= next_tick:
                next_tick = max(next_tick + tick_s, time.monotonic())  # no burst of late ticks
                yield Event("tick")
                continue
            delivered = False
            for sub, names in self._subscribers:
                msg = sub.recv(timeout=0)
                if msg is not None:
                    delivered = True
                    yield Event("message", names.get(msg.header.topic, msg.header.topic), msg)
                    if self.stopping:
                        return
            if delivered:
                continue
            wait = POLL_S if next_tick is None else min(POLL_S, max(0.0, next_tick - time.monotonic()))
            if self._subscribers:
                self._poller.poll(int(wait * 1000) + 1)
            else:
                self.stop_signals.event.wait(wait)

    # -- hooks --------------------------------------------------------------------------------------

    @classmethod
    def prepare(cls, params) -> None:
        """Do ahead what does not need the bus (import torch, the avatar package, load kernels):
        a standby copy runs this while it waits, so when it takes over its setup is short."""

    def setup(self) -> None:
        """Subscribe, open files and models. The node counts as ready when this returns."""

    def on_message(self, topic: str, msg: Message) -> None:
        """A message arrived on ``topic`` (the name given to :meth:`subscribe`)."""

    def on_tick(self) -> None:
        """Called every :attr:`tick_s` seconds."""

    def teardown(self) -> None:
        """Flush what the node owes (runs on every exit, also after a failure)."""

    def run(self) -> None:
        """The node's loop; by default dispatches :meth:`events` to the hooks."""
        for event in self.events(self.tick_s):
            if event.kind == "tick":
                self.on_tick()
            else:
                self.on_message(event.topic, event.message)
                self.acknowledge(event.message, event.topic)

    # -- life cycle -----------------------------------------------------------------------------------

    def execute(self) -> int:
        """setup, heartbeat, run, teardown, close; the exit code (0 ok, 1 failed)."""
        try:
            self.setup()
            self._check_ack_topics()
            if self.heartbeat is not None:
                # A launcher waits for this first heartbeat: give its subscription a moment to
                # reach us (PUB/SUB drops what is sent before), then beat.
                self.bus.publisher.wait_for_subscribers("node/status", timeout=0.5)
                self.heartbeat.start()
            self.log.info("running (pid %d)", os.getpid())
            self.run()
        except KeyboardInterrupt:  # a second Ctrl-C / SIGTERM: skip the rest of the work
            self.log.warning("interrupted")
        except NodeError as exc:
            self.log.error("failed: %s", exc)
            self.error(str(exc))
            self.set_state("error")
            self.exit_code = 1
        except Exception as exc:
            self.log.exception("failed: %s", exc)
            self.error(f"{type(exc).__name__}: {exc}")
            self.set_state("error")
            self.exit_code = 1
        finally:
            self.close()
        return self.exit_code

    def close(self) -> None:
        self.set_state("stopping")
        self._closing = True
        try:
            self.teardown()
            if self._owed:  # let what teardown published leave before LINGER-0 sockets close
                time.sleep(self.linger_s)
        except KeyboardInterrupt:
            self.log.warning("teardown interrupted")
        except Exception as exc:
            self.log.exception("teardown failed: %s", exc)
            self.exit_code = 1
        finally:
            self.bus.close()
        if self.stop_signals.signal_name:
            self.log.info("stopped (%s)", self.stop_signals.signal_name)


def name_process(name: str) -> None:
    """Log lines of this process carry ``name`` (stg_node.logs' format shows the process name)."""
    multiprocessing.current_process().name = name
