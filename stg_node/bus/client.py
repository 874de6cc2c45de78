"""Bus: one node's connection to the bus, the object a node runtime holds.

    with Bus("ipc:///tmp/stg/bus", node="tracker") as bus:
        frames = bus.subscribe("camera/frame")
        for frame in frames:                        # Ctrl-C ends it; the with-block cleans up
            bus.publish(BodyPose(...))

It owns a ZeroMQ context, one thread-safe Publisher, the Subscribers made through it and
a Heartbeat (NodeStatus every ``heartbeat_s``, with all of their counters). Closing it
closes every socket with LINGER 0 and terminates the context: it never hangs on
messages that cannot be delivered.
"""

from __future__ import annotations

import zmq

from stg_node.bus import security
from stg_node.bus.config import BusConfig, as_config
from stg_node.bus.heartbeat import Heartbeat
from stg_node.bus.messages import Message
from stg_node.bus.pubsub import Publisher, Subscriber, default_node_id


class Bus:
    """A node's publisher, subscribers and heartbeat on one context.

    ``bind=True`` runs without a broker (the publisher binds the subscriber-side endpoints).
    ``heartbeat_s=0`` disables the heartbeat.
    """

    def __init__(
        self,
        config: BusConfig | str | None = None,
        *,
        node: str | None = None,
        heartbeat_s: float = 1.0,
        bind: bool = False,
    ):
        self.config = as_config(config)
        self.node = node or default_node_id()
        self.context = zmq.Context()
        self.subscribers: list[Subscriber] = []
        self.heartbeat: Heartbeat | None = None
        self._closed = False
        try:
            self.publisher = Publisher(self.config, node=self.node, context=self.context, bind=bind)
            if heartbeat_s > 0:
                self.heartbeat = Heartbeat(self.publisher, period_s=heartbeat_s).start()
        except BaseException:
            self.close()
            raise

    def publish(self, msg: Message, topic: str | None = None, *, stamp_ns: int | None = None) -> int:
        return self.publisher.publish(msg, topic, stamp_ns=stamp_ns)

    def subscribe(self, *topics, **options) -> Subscriber:
        """A new Subscriber on ``topics`` (see Subscriber), counted in this node's heartbeat."""
        sub = Subscriber(self.config, topics, context=self.context, **options)
        self.subscribers.append(sub)
        if self.heartbeat is not None:
            self.heartbeat.add(sub)
        return sub

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self.heartbeat is not None:
            self.heartbeat.stop()
        for sub in self.subscribers:
            sub.close()
        publisher = getattr(self, "publisher", None)
        if publisher is not None:
            publisher.close()
        security.stop_authenticator(self.context)
        self.context.term()

    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["Bus", "default_node_id"]
