"""Topic names, namespaces and lanes (the per-topic delivery policies).

A topic is ``[namespace/]name`` where ``name`` is one of the standard names below
(``camera/frame`` ...) or any custom name. The standard name decides the message type
that may appear on the topic and the lane that carries it.

Why lanes: ZeroMQ's high-water mark (HWM) and its drop behaviour belong to a socket,
not to a topic, and ZMQ_CONFLATE cannot carry multipart messages. A 6 MB camera frame
queued behind a slow reader must not push a 500-byte pose out of the same queue. So
each policy gets its own pair of sockets ("lane"), with HWMs sized for what it carries:

- ``latest``   keep-last. HWM 4 at every hop; a subscriber's reader thread drains its
               socket continuously and hands out only the newest message per topic (older
               ones are counted as ``superseded``). Camera frames and rendered images.
               Not 2: libzmq's sender learns of reads through throttled commands, so with
               HWM 2 two quick sends can meet a "full" queue that is in fact empty.
- ``reliable`` lossless small messages. HWM 10000 at every hop (about 5 MB of poses, 5 min
               at 30 Hz); delivered in order; any sequence gap is counted as ``lost``.
- ``bulk``     lossless large, rare messages: Gaussian snapshots. HWM 16 so that a stalled
               reader cannot pin gigabytes; latched by the broker (last-value cache).

PUB/SUB cannot be lossless against a reader that stops for good; "lossless" here means:
never dropped by policy, queues deep enough for the traffic, and every loss is detected
(sequence numbers) and counted in NodeStatus.drops.
"""

from __future__ import annotations

from collections.abc import Container
from dataclasses import dataclass

from stg_node.bus.spec import MAX_TOPIC_BYTES, TOPIC_PATTERN


@dataclass(frozen=True)
class Lane:
    name: str
    index: int  # tcp port offset = 2 * index (+1 for the subscriber side)
    keep_last: bool
    hwm: int
    doc: str


LANES: dict[str, Lane] = {
    "latest": Lane("latest", 0, True, 4, "keep-last: large high-rate messages where only the newest matters"),
    "reliable": Lane("reliable", 1, False, 10_000, "lossless, in order: small messages"),
    "bulk": Lane("bulk", 2, False, 16, "lossless, large and rare; latched topics live here"),
}
DEFAULT_LANE = "reliable"


def check_topic(topic: str) -> str:
    """Return ``topic`` if it is a valid topic name, else raise ValueError saying why."""
    if not isinstance(topic, str) or not topic:
        raise ValueError(f"a topic must be a non-empty string, got {topic!r}")
    if len(topic.encode()) > MAX_TOPIC_BYTES:
        raise ValueError(f"topic {topic[:40]!r}... is longer than {MAX_TOPIC_BYTES} bytes")
    if not TOPIC_PATTERN.match(topic):
        raise ValueError(
            f"topic {topic!r} is not valid: use /-separated parts of letters, digits, '_', '-', '.'"
        )
    return topic


def check_namespace(namespace: str) -> str:
    if namespace:
        check_topic(namespace)
    return namespace


def join_namespace(namespace: str, topic: str) -> str:
    """``avatar/image`` -> ``rig1/avatar/image``; a leading ``/`` means absolute (no namespace)."""
    if topic.startswith("/"):
        return check_topic(topic[1:])
    check_topic(topic)
    return f"{namespace}/{topic}" if namespace else topic


def base_name(topic: str, standard: Container[str]) -> str | None:
    """The standard topic name a full topic ends with (``rig1/camera/frame`` -> ``camera/frame``).

    ``standard`` is normally messages.TOPIC_TYPES, the one table of standard topics."""
    parts = topic.rsplit("/", 2)
    if len(parts) >= 2:
        tail = f"{parts[-2]}/{parts[-1]}"
        if tail in standard:
            return tail
    return None
