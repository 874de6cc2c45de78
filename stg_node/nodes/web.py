"""The web node: the running system in a browser, from a page shipped in the package (plain
HTML and JavaScript in ``web_static/``: no CDN, no build step), images over a WebSocket.

    stg-node web --port 8080                     # http://localhost:8080/avatar  /  http://localhost:8080/

- ``/avatar``: the live avatar, full window, nothing else: what a telepresence robot's screen
  shows (``?stats=1`` adds the frame age in a corner).
- ``/``: the operator's page: the avatar; the camera with the person mask and the body's skeleton
  over it; every node's health (state, heartbeat age, message rates, drops, errors); the
  trainer's figures (iteration, loss, PSNR, Gaussians, active-motion fraction); the frame age of
  this page and of every other page (a robot's screen reports its own).

Frame age is measured on the page: from the image's publish stamp (``stamp_ns`` of its bus
message) to the moment it is drawn, on the server's clock (the page estimates its offset from
ping round trips, NTP-style), so it holds when the browser runs on another machine.

Work is done only for what a page shows: an image is encoded (JPEG) only while a connected
page wants its stream, keep-last topics hand the node only their newest message, and a client
that lags loses frames, counted (``slow_client`` in NodeStatus drops), instead of queueing them
(:mod:`.web_server`). The avatar follows one steady camera (``avatar_view: steady``): the
renderer's default views alternate between the training camera and a turning orbit; a view
whose camera repeats (the training camera, a robot's standing view) is shown, a camera that never
repeats (the orbit) only while nothing else comes.

Bound to 127.0.0.1 by default; any other ``host`` needs ``STG_WEB_TOKEN`` (web_server.token_policy),
and the node says so when it starts.
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Literal

import numpy as np

from stg_node.bus import BodyPose, Frame, NodeStatus, RenderedImage, TrainerMetrics
from stg_node.bus.foxglove_views import encode_image, json_safe
from stg_node.nodes.live_scene import BodySkeleton, project_points
from stg_node.nodes.params import param
from stg_node.nodes.runtime import Node, NodeError
from stg_node.nodes.web_server import WebServer, WebServerError, is_loopback, token_policy

#: Cameras of recent frames kept to project a pose onto the frame it was estimated from.
RECENT_FRAMES = 16
#: Mask overlay colour (RGB) and opacity on the camera image.
MASK_RGB = (40, 200, 255)
MASK_ALPHA = 110
#: steady view: how long a camera counts as seen, and the rounding that makes two cameras equal.
STEADY_WINDOW_S = 2.0
CAMERA_DECIMALS = 4


@dataclass
class WebParams:
    host: str = param(
        "127.0.0.1", doc="address to listen on (127.0.0.1: this machine only; any other needs STG_WEB_TOKEN)"
    )
    port: int = param(8080, min=0, max=65535, doc="TCP port of the page (0: any free port, logged)")
    jpeg_quality: int = param(85, min=1, max=100, doc="JPEG quality of the images sent to pages")
    camera_max_side: int = param(
        640, min=16, max=4096, unit="px", doc="camera images are scaled down to this"
    )
    avatar_view: Literal["steady", "all"] = param(
        "steady", doc="steady: follow a camera that repeats (not a turning orbit); all: every avatar image"
    )
    status_period_s: float = param(1.0, min=0.1, unit="s", doc="node health and trainer figures this often")
    report_every_s: float = param(
        10.0, min=0.0, unit="s", doc="log the pages' frame age this often (0: never)"
    )
    body_model: str | None = param(
        None, doc="SMPL model for the skeleton (default: the open body, as the trainer's default)"
    )


class SteadyView:
    """Which avatar images to show when several cameras are rendered (see the module docstring)."""

    def __init__(self, window_s: float = STEADY_WINDOW_S):
        self.window_s = window_s
        self.seen: dict[bytes, float] = {}  # camera key -> last time seen
        self.last_repeat = -math.inf

    @staticmethod
    def key(msg: RenderedImage) -> bytes:
        parts = (msg.K, msg.R, msg.t, np.asarray(msg.image.shape[:2], np.float64))
        return b"".join(np.round(np.asarray(p, np.float64), CAMERA_DECIMALS).tobytes() for p in parts)

    def accept(self, msg: RenderedImage, now: float) -> bool:
        key = self.key(msg)
        repeated = key in self.seen and now - self.seen[key] <= self.window_s
        self.seen[key] = now
        if len(self.seen) > 64:  # an orbit adds a key per image: forget the old ones
            for old in [k for k, t in self.seen.items() if now - t > self.window_s]:
                del self.seen[old]
        if repeated:
            self.last_repeat = now
            return True
        return now - self.last_repeat > self.window_s  # nothing steady lately: show what there is


def scaled(image: np.ndarray, K: np.ndarray, max_side: int) -> tuple[np.ndarray, np.ndarray]:
    """The image scaled down to ``max_side`` (never up) and its intrinsics scaled alike."""
    h, w = image.shape[:2]
    scale = min(1.0, max_side / max(h, w))
    if scale >= 1.0:
        return image, np.asarray(K, np.float64)
    import cv2

    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    out = cv2.resize(np.ascontiguousarray(image), size, interpolation=cv2.INTER_AREA)
    sx, sy = size[0] / w, size[1] / h
    K2 = np.asarray(K, np.float64).copy()
    K2[0] *= sx
    K2[1] *= sy
    return out, K2


def mask_overlay(mask: np.ndarray) -> np.ndarray:
    """(H, W, 4) RGBA: the mask's colour where the person is, transparent elsewhere."""
    rgba = np.zeros((*mask.shape, 4), np.uint8)
    on = mask > 127
    rgba[on, :3] = MASK_RGB
    rgba[on, 3] = MASK_ALPHA
    return rgba


class WebNode(Node):
    """Serves the page and its live streams (see the module docstring)."""

    kind = "web"
    Params = WebParams
    tick_s = 0.25
    server: WebServer | None = None  # set in setup, stopped in teardown

    def setup(self) -> None:
        p = self.params
        try:
            token = token_policy(p.host)
            self.server = WebServer(p.host, p.port, token=token)
            port = self.server.start()
        except WebServerError as exc:
            raise NodeError(str(exc)) from exc
        shown = "localhost" if is_loopback(p.host) else p.host
        query = "?token=$STG_WEB_TOKEN" if token else ""
        self.log.info(
            "page on http://%s:%d/%s (operator) and http://%s:%d/avatar%s (robot screen)",
            shown, port, query, shown, port, query,
        )  # fmt: skip
        if token is not None:
            self.log.info(
                "a token is required (STG_WEB_TOKEN; %s): open the page with ?token=<its value>",
                "bound beyond this machine" if not is_loopback(p.host) else "set in the environment",
            )
        self.steady = SteadyView()
        self.cameras: OrderedDict[int, tuple[np.ndarray, np.ndarray, np.ndarray, int, int]] = OrderedDict()
        self.skeleton = BodySkeleton(p.body_model)  # loads torch and the body in a thread of its own
        self.skeleton.start_warm_up()
        self.nodes: dict[str, dict] = {}
        self.metrics: TrainerMetrics | None = None
        self.next_status = 0.0
        self.drops_counted = 0  # server.drops already in our NodeStatus
        self.next_report = time.monotonic() + p.report_every_s
        self.subscribe("avatar/image", keep_last=True)
        self.subscribe("camera/frame", keep_last=True)
        # Every pose (small, lossless): the pose of a frame comes after it, and a keep-last pose
        # would be overtaken by the next before the frame it belongs to is matched.
        self.poses = self.subscribe("body/pose", keep_last=False)
        self.statuses = self.subscribe("node/status")
        self.subscribe("trainer/metrics", keep_last=True)

    def run(self) -> None:
        """The runtime's loop, but node/status and body/pose drained whole each round: taken one
        message per round beside the images, they would fall behind."""
        for event in self.events(self.tick_s):
            if event.kind == "tick":
                self.on_tick()
                continue
            self.on_message(event.topic, event.message)
            for name, sub in (("node/status", self.statuses), ("body/pose", self.poses)):
                while not self.stopping and (msg := sub.recv(timeout=0)) is not None:
                    self.on_message(name, msg)

    # -- messages ------------------------------------------------------------------------------------------

    def on_message(self, topic: str, msg) -> None:
        if isinstance(msg, RenderedImage):
            self._avatar(msg)
        elif isinstance(msg, Frame):
            self._camera(msg)
        elif isinstance(msg, BodyPose):
            self._skeleton(msg)
        elif isinstance(msg, NodeStatus):
            self.nodes[msg.node] = {
                "state": msg.state,
                "pid": msg.pid,
                "host": msg.host,
                "uptime_s": msg.uptime_s,
                "period_s": msg.period_s,
                "stamp_ns": msg.header.stamp_ns,
                "rates_hz": msg.rates_hz,
                "drops": msg.drops,
                "errors": msg.errors,
                "last_error": msg.last_error,
            }
        elif isinstance(msg, TrainerMetrics):
            self.metrics = msg

    def _avatar(self, msg: RenderedImage) -> None:
        server = self.server
        if not server.wants("avatar"):
            return
        if self.params.avatar_view == "steady" and not self.steady.accept(msg, time.monotonic()):
            self.drop("other_view")
            return
        h, w = msg.image.shape[:2]
        meta = {
            "seq": msg.header.seq,
            "stamp_ns": msg.header.stamp_ns,
            "src": msg.header.src,
            "width": w,
            "height": h,
            "snapshot_version": msg.snapshot_version,
            "latency_ms": msg.latency_ms,
        }
        server.publish("avatar", meta, encode_image(msg.image, "jpeg", self.params.jpeg_quality))

    def _camera(self, msg: Frame) -> None:
        server = self.server
        wants_camera, wants_mask = server.wants("camera"), server.wants("mask") and msg.mask is not None
        if not (wants_camera or wants_mask or server.wants("skeleton")):
            return
        image, K = scaled(msg.image, msg.K, self.params.camera_max_side)
        h, w = image.shape[:2]
        camera = (K, np.asarray(msg.R, np.float64), np.asarray(msg.t, np.float64), w, h)
        self.cameras[msg.header.seq] = camera
        while len(self.cameras) > RECENT_FRAMES:
            self.cameras.popitem(last=False)
        meta = {
            "seq": msg.header.seq,
            "stamp_ns": msg.header.stamp_ns,
            "index": msg.index,
            "width": w,
            "height": h,
        }
        if wants_camera:
            server.publish("camera", meta, encode_image(image, "jpeg", self.params.jpeg_quality))
        if wants_mask:
            mask, _ = scaled(msg.mask, msg.K, self.params.camera_max_side)
            server.publish("mask", meta, encode_image(mask_overlay(mask), "png"))

    def _skeleton(self, pose: BodyPose) -> None:
        if not self.server.wants("skeleton") or not self.skeleton.ready.is_set() or self.skeleton.failure:
            return
        camera = self.cameras.get(pose.frame_seq)  # the camera of the very frame the pose is of
        if camera is None:  # a frame we skipped (keep-last) or of another rig: no picture to go on
            return
        joints = self.skeleton.joints(pose)
        K, R, t, w, h = camera
        uv, front = project_points(joints, K, R, t)
        points = [
            [round(float(u), 1), round(float(v), 1)] if ok else None
            for (u, v), ok in zip(uv, front, strict=True)
        ]
        self.server.publish(
            "skeleton",
            {
                "seq": pose.header.seq,
                "stamp_ns": pose.header.stamp_ns,
                "frame_seq": pose.frame_seq,
                "width": w,
                "height": h,
                "confidence": json_safe(pose.confidence),
                "parents": list(self.skeleton.parents),
                "points": points,
            },
        )

    # -- periodic ------------------------------------------------------------------------------------------

    def on_tick(self) -> None:
        drops = self.server.drops  # counted in the server's thread; moved into NodeStatus here
        if drops > self.drops_counted:
            self.drop("slow_client", drops - self.drops_counted)
            self.drops_counted = drops
        now = time.monotonic()
        if now >= self.next_status and self.server.wants("status"):
            self.next_status = now + self.params.status_period_s
            self.server.publish("status", self._status())
        if self.params.report_every_s and now >= self.next_report:
            self.next_report = now + self.params.report_every_s
            self._log_pages()

    def _status(self) -> dict:
        now_ns = time.time_ns()
        nodes = {}
        for name, s in sorted(self.nodes.items()):
            age = (now_ns - s["stamp_ns"]) / 1e9 if s["stamp_ns"] else None
            alive = age is not None and age <= 3 * max(s["period_s"], 0.1)
            nodes[name] = {**s, "heartbeat_age_s": age, "alive": alive}
        trainer = None
        if self.metrics is not None:
            m = self.metrics
            trainer = {
                "src": m.header.src,
                "iteration": m.iteration,
                "loss": m.loss,
                "psnr": m.psnr,
                "num_gaussians": m.num_gaussians,
                "active_motion_fraction": m.extra.get("active_motion_fraction"),
                "it_per_s": m.it_per_s,
                "model_version": m.model_version,
                "elapsed_s": m.elapsed_s,
            }
        return json_safe(
            {"server_ns": now_ns, "nodes": nodes, "trainer": trainer, "web": self.server.stats()}
        )

    def _log_pages(self) -> None:
        for client in self.server.stats()["clients"]:
            age = client["report"].get("avatar") or {}
            if age.get("shown"):
                self.log.info(
                    "page %s (client %d): %d avatar frames shown, frame age p50 %.0f ms, p95 %.0f ms; "
                    "%d dropped",
                    client["report"].get("page", "?"),
                    client["id"],
                    age["shown"],
                    age.get("age_p50_ms") or 0.0,
                    age.get("age_p95_ms") or 0.0,
                    client["drops"],
                )

    def teardown(self) -> None:
        if self.server is not None:
            self._log_pages()
            self.server.stop()
            self.log.info(
                "served %d messages to pages, %d dropped for pages that lagged",
                self.server.sent,
                self.server.drops,
            )
