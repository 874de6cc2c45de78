"""The foxglove node: the running system, live, in Foxglove (the Foxglove WebSocket protocol,
served by Foxglove's own SDK, foxglove-sdk).

    stg-node foxglove --port 8765            # then in Foxglove: Open connection -> Foxglove WebSocket
                                             # -> ws://localhost:8765

It serves, for each bus topic in ``topics``, the view channels of
:mod:`stg_node.bus.foxglove_views` (the same names and schemas as ``stg-bag export --foxglove``):
the avatar (``view/avatar/image/image``) and the camera frames as CompressedImage, masks and
alpha as RawImage, CameraCalibration and FrameTransform per camera, the body as a SceneUpdate
skeleton (and its root and joints) in ``world``, the latest avatar snapshot posed with the latest
body pose as a coloured PointCloud (``view/avatar/snapshot/cloud``), and every message's scalar
fields as JSON (``view/<topic>/fields``: node status, the trainer's loss, PSNR, Gaussian count
and ``extra.active_motion_fraction``), for Plot panels.

Costs are paid only for what someone watches: a view is built only while a client subscribes
to its channel (``Channel.has_sinks()``: a JPEG costs milliseconds, the point cloud poses the
whole avatar), and the cloud at most ``cloud_rate_hz``. Nothing queues for a slow client:
keep-last topics hand the node only their newest message (older ones are counted as
``superseded``), and each client has an outbox of ``backlog`` messages in the SDK whose oldest
message is dropped when a client does not keep up; ``log`` never blocks, so a stalled client
never slows the node, and the node never slows the bus. The SDK reports an overflowing outbox in
its log (at most once per 30 s per process); the node counts those reports as
``client_backlog`` drops in its NodeStatus.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Literal

import numpy as np

from stg_node.bus import BodyPose, Frame, GaussianSnapshot, RenderedImage
from stg_node.bus.codec import expected_type
from stg_node.bus.foxglove_views import (
    fields_json_schema,
    message_class,
    message_views,
    point_cloud,
    type_views,
    view_topic,
    wire_parts,
)
from stg_node.nodes.avatar_adapter import DEFAULT_MODULE
from stg_node.nodes.live_scene import BodySkeleton
from stg_node.nodes.params import param
from stg_node.nodes.runtime import Node, NodeError
from stg_node.nodes.web_server import is_loopback

#: The bus topics served by default (names before remaps and namespace).
DEFAULT_TOPICS = [
    "avatar/image",
    "camera/frame",
    "body/pose",
    "avatar/snapshot",
    "trainer/metrics",
    "node/status",
]
#: The SDK logs a full client outbox on this logger (rust target foxglove::websocket::...).
SDK_OUTBOX_LOGGER = "foxglove.websocket"
SDK_OUTBOX_TEXT = "outbox for client"
#: Types whose newest message is all a viewer needs (keep-last subscriptions).
KEEP_LAST_TYPES = (Frame, RenderedImage, BodyPose, GaussianSnapshot)


@dataclass
class FoxgloveParams:
    host: str = param(
        "127.0.0.1",
        doc="address to listen on (127.0.0.1: this machine only; 0.0.0.0: every interface, which the "
        "Foxglove protocol cannot protect with a login)",
    )
    port: int = param(
        8765, min=0, max=65535, doc="TCP port of the Foxglove WebSocket (0: any free port, logged)"
    )
    topics: list[str] = param(DEFAULT_TOPICS, doc="bus topics to serve (names as subscribed, before remaps)")
    image_format: Literal["jpeg", "png"] = param("jpeg", doc="images as CompressedImage: jpeg or png")
    jpeg_quality: int = param(85, min=1, max=100, doc="JPEG quality of the images")
    cloud_rate_hz: float = param(
        2.0, min=0.0, unit="Hz", doc="point cloud of the avatar at most this often (0: off)"
    )
    cloud_max_points: int = param(50_000, min=1, doc="the most opaque Gaussians kept in the point cloud")
    avatar: str = param(DEFAULT_MODULE, doc="package implementing the avatar API (the point cloud)")
    device: str = param("cpu", doc="torch device for posing the point cloud")
    body_model: str | None = param(
        None, doc="SMPL model for the skeleton before a snapshot arrives (default: the open body)"
    )
    backlog: int = param(16, min=1, doc="messages queued per client before the oldest are dropped")


class _OutboxReports(logging.Handler):
    """Counts the SDK's 'outbox for client ... full' reports (one per overflow episode), in the
    SDK's thread; the node moves the count into its NodeStatus on its ticks."""

    def __init__(self):
        super().__init__(logging.INFO)
        self.count = 0

    def emit(self, record: logging.LogRecord) -> None:
        if SDK_OUTBOX_TEXT in record.getMessage():
            self.count += 1


class _Subscriptions:
    """ServerListener: logs who watches what (the SDK calls it from its own threads)."""

    def __init__(self, log: logging.Logger):
        self.log = log

    def on_subscribe(self, client, channel) -> None:
        self.log.info("client %d watches %s", client.id, channel.topic)

    def on_unsubscribe(self, client, channel) -> None:
        self.log.info("client %d stopped watching %s", client.id, channel.topic)


class FoxgloveNode(Node):
    """Serves the bus to Foxglove over its WebSocket protocol (see the module docstring)."""

    kind = "foxglove"
    Params = FoxgloveParams
    tick_s = 0.5  # the point cloud is refreshed on ticks too (a still body, a new snapshot)
    # Set in setup (what teardown releases): the SDK server, the log hook, the point cloud.
    server = None
    outbox_reports: logging.Handler | None = None
    cloud = None  # live_scene.AvatarCloud, created when someone watches the cloud

    def setup(self) -> None:
        import foxglove

        p = self.params
        self.skeleton = BodySkeleton(p.body_model)  # loads torch and the body in a thread of its own
        self.skeleton.start_warm_up()
        self.snapshot: GaussianSnapshot | None = None
        self.pose: BodyPose | None = None
        self.camera_center: np.ndarray | None = None
        self.next_cloud = 0.0
        self.sent: dict[str, int] = {}
        self.outbox_reports = _OutboxReports()
        self.reports_counted = 0
        sdk_log = logging.getLogger(SDK_OUTBOX_LOGGER)
        sdk_log.addHandler(self.outbox_reports)
        if sdk_log.getEffectiveLevel() > logging.INFO:
            sdk_log.setLevel(logging.INFO)
        foxglove.set_log_level("INFO")  # the SDK's own lines (clients, overflows) into our log

        self.drained: list = []  # (name, Subscriber) of lossless topics, drained whole each round
        self.channels: dict[str, object] = {}  # view channel -> foxglove channel
        self.served: dict[str, type] = {}  # full bus topic -> message type
        for name in p.topics:
            cls = expected_type(self.bus.config.topic(self.topic(name)))
            if cls is None:
                raise NodeError(f"topic {name!r} has no known message type: name a standard topic")
            full = self.bus.config.topic(self.topic(name))
            self.served[full] = cls
            self._advertise(full, cls)
            sub = self.subscribe(name, keep_last=True if cls in KEEP_LAST_TYPES else None)
            if cls not in KEEP_LAST_TYPES:
                self.drained.append((name, sub))
        try:
            self.server = foxglove.start_server(
                name=f"stg_node {self.name}",
                host=p.host,
                port=p.port,
                server_listener=_Subscriptions(self.log),
                message_backlog_size=p.backlog,
            )
        except Exception as exc:  # the SDK raises RuntimeError for a port in use or a bad address
            raise NodeError(f"cannot serve Foxglove on {p.host}:{p.port}: {exc}") from exc
        self.log.info(
            "Foxglove WebSocket on ws://%s:%d (%d channels); in Foxglove: Open connection -> "
            "Foxglove WebSocket -> ws://%s:%d",
            p.host,
            self.server.port,
            len(self.channels),
            "localhost" if is_loopback(p.host) else p.host,
            self.server.port,
        )
        if not is_loopback(p.host):
            self.log.warning(
                "listening on %s: anyone who reaches port %d sees this session (the Foxglove WebSocket "
                "protocol has no login); prefer host 127.0.0.1 and an SSH tunnel",
                p.host,
                self.server.port,
            )

    def run(self) -> None:
        """The runtime's loop, but lossless topics (node/status: one topic for every node) drained
        whole each round, where one message per round would let them fall behind the images."""
        for event in self.events(self.tick_s):
            if event.kind == "tick":
                self.on_tick()
                continue
            self.on_message(event.topic, event.message)
            for name, sub in self.drained:
                while not self.stopping and (msg := sub.recv(timeout=0)) is not None:
                    self.on_message(name, msg)

    def _advertise(self, full_topic: str, cls: type) -> None:
        """Create every view channel of a topic now, so clients can subscribe before data flows."""
        import foxglove
        import foxglove.channels

        for view in type_views(cls.SPEC.type):
            channel_name = view_topic(full_topic, view.name)
            if view.schema == "json":
                channel = foxglove.Channel(channel_name, schema=fields_json_schema(cls.SPEC.type))
            else:
                channel_cls = getattr(foxglove.channels, f"{message_class(view.schema).__name__}Channel")
                channel = channel_cls(channel_name)
            self.channels[channel_name] = channel

    def _watched(self, channel_name: str) -> bool:
        channel = self.channels.get(channel_name)
        return channel is not None and channel.has_sinks()

    def _log(self, channel_name: str, view, stamp_ns: int) -> None:
        self.channels[channel_name].log(view, log_time=stamp_ns or time.time_ns())
        self.sent[channel_name] = self.sent.get(channel_name, 0) + 1

    # -- messages ----------------------------------------------------------------------------------

    def on_message(self, topic: str, msg) -> None:
        full = msg.header.topic
        header, arrays = wire_parts(msg)
        if isinstance(msg, GaussianSnapshot):
            self._take_snapshot(msg)
        elif isinstance(msg, BodyPose):
            self.pose = msg
            if arrays.get("joints") is None and self._body_watched(full):
                if self.skeleton.ready.is_set() and not self.skeleton.failure:  # until then: none
                    arrays["joints"] = self.skeleton.joints(msg)
            self._maybe_cloud()
        elif isinstance(msg, Frame):
            R, t = np.asarray(msg.R, np.float64), np.asarray(msg.t, np.float64)
            self.camera_center = -R.T @ t
        views = message_views(
            full,
            header,
            arrays,
            image_format=self.params.image_format,
            jpeg_quality=self.params.jpeg_quality,
            wanted=self._watched,
        )
        for channel_name, view in views:
            self._log(channel_name, view, msg.header.stamp_ns)

    def _body_watched(self, full_topic: str) -> bool:
        return self._watched(view_topic(full_topic, "skeleton")) or self._watched(
            view_topic(full_topic, "joints")
        )

    def _take_snapshot(self, msg: GaussianSnapshot) -> None:
        self.snapshot = msg
        self.skeleton.use_snapshot(msg)
        if self.cloud is not None:
            self.cloud.submit(msg)
        self._maybe_cloud(force=True)

    def _cloud_channel(self) -> str | None:
        for full, cls in self.served.items():
            if cls is GaussianSnapshot:
                return view_topic(full, "cloud")
        return None

    def _maybe_cloud(self, force: bool = False) -> None:
        """Publish the posed point cloud when someone watches it, at most cloud_rate_hz."""
        p = self.params
        channel_name = self._cloud_channel()
        if p.cloud_rate_hz <= 0 or channel_name is None or not self._watched(channel_name):
            return
        now = time.monotonic()
        if now < self.next_cloud and not force:
            return
        if self.snapshot is None or self.pose is None:
            return
        if self.cloud is None:
            from stg_node.nodes.live_scene import AvatarCloud

            self.cloud = AvatarCloud(
                module=p.avatar, device=p.device, max_points=p.cloud_max_points, on_error=self.error
            )
            self.cloud.submit(self.snapshot)
        cloud = self.cloud.cloud(self.pose, self.camera_center)
        if cloud is None:
            return  # the snapshot is still loading: the next pose tries again
        self.next_cloud = now + 1.0 / p.cloud_rate_hz
        stamp = self.pose.header.stamp_ns
        self._log(channel_name, point_cloud(cloud.positions, cloud.colors, stamp, cloud.alpha), stamp)

    def on_tick(self) -> None:
        reports = self.outbox_reports.count
        if reports > self.reports_counted:
            self.drop("client_backlog", reports - self.reports_counted)
            self.reports_counted = reports
        self._maybe_cloud()

    def teardown(self) -> None:
        if self.outbox_reports is not None:
            logging.getLogger(SDK_OUTBOX_LOGGER).removeHandler(self.outbox_reports)
        if self.cloud is not None:
            self.cloud.close()
        if self.server is not None:
            self.server.stop()
            sent = ", ".join(f"{k} {v}" for k, v in sorted(self.sent.items())) or "nothing"
            self.log.info("served %s", sent)
