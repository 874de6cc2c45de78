"""The message bus: ZeroMQ multipart messages with msgpack headers and zero-copy arrays.

Wire format and schemas: proto/ (language-neutral) and docs/BUS.md (how to use it).
This package never imports torch, so robot-side tools start fast and stay small.

    from stg_node.bus import Bus, BodyPose
    with Bus(node="tracker") as bus:
        for frame in bus.subscribe("camera/frame"):
            bus.publish(BodyPose(...))
"""

from stg_node.bus.broker import Broker, BrokerRunning
from stg_node.bus.client import Bus
from stg_node.bus.codec import Envelope, decode, decode_envelope, encode
from stg_node.bus.config import BusConfig, default_url, lane_endpoint
from stg_node.bus.heartbeat import Heartbeat, NodeMonitor
from stg_node.bus.messages import (
    REGISTRY,
    Ack,
    BodyPose,
    Frame,
    GaussianSnapshot,
    Header,
    Message,
    NodeStatus,
    RenderedImage,
    TrainerMetrics,
    ViewRequest,
)
from stg_node.bus.pubsub import Publisher, Subscriber
from stg_node.bus.spec import DROP_REASONS, MessageError
from stg_node.bus.topics import LANES

__all__ = [
    "DROP_REASONS",
    "LANES",
    "REGISTRY",
    "Ack",
    "BodyPose",
    "Broker",
    "BrokerRunning",
    "Bus",
    "BusConfig",
    "Envelope",
    "Frame",
    "GaussianSnapshot",
    "Header",
    "Heartbeat",
    "Message",
    "MessageError",
    "NodeMonitor",
    "NodeStatus",
    "Publisher",
    "RenderedImage",
    "Subscriber",
    "TrainerMetrics",
    "ViewRequest",
    "decode",
    "decode_envelope",
    "default_url",
    "encode",
    "lane_endpoint",
]
