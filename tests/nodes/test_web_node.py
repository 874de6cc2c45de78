"""The web node and its server, seen through plain HTTP and WebSocket clients (urllib, websockets):
the page and its files, the streams a page subscribes to (and only those encoded), a page that
stops reading (it loses frames, counted; the others and the bus do not wait), the avatar's steady
view, and the token policy beyond this machine."""

from __future__ import annotations

import contextlib
import json
import socket
import struct
import time
import urllib.error
import urllib.request

import cv2
import numpy as np
import pytest
from nodehelpers import NodeThread, wait_until

from stg_node.bus import BodyPose, Bus, BusConfig, Frame, RenderedImage
from stg_node.nodes import web as web_module
from stg_node.nodes.params import parse_params
from stg_node.nodes.runtime import NodeError
from stg_node.nodes.web import SteadyView, WebNode, WebParams
from stg_node.nodes.web_server import TOKEN_COOKIE, WebServer, WebServerError, is_loopback, token_policy

K = np.array([[80.0, 0, 32], [0, 80.0, 24], [0, 0, 1]])
RNG = np.random.default_rng(9)
TOKEN = "0123456789abcdef0123"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def web_node(bus_url, **params) -> WebNode:
    values = {"port": free_port(), "status_period_s": 0.2, **params}
    return WebNode("web", parse_params(WebParams, values), BusConfig(url=bus_url), heartbeat_s=0.2)


def http(url: str, headers: dict | None = None) -> tuple[int, dict, bytes]:
    request = urllib.request.Request(url, headers=headers or {})
    try:
        with urllib.request.urlopen(request, timeout=10) as response:
            return response.status, dict(response.headers), response.read()
    except urllib.error.HTTPError as exc:
        return exc.code, dict(exc.headers), exc.read()


@contextlib.contextmanager
def page(port: int, streams, *, max_queue: int | None = 16, headers=None, query: str = ""):
    """A WebSocket client as the page opens it, subscribed to ``streams``."""
    from websockets.sync.client import connect

    with connect(f"ws://127.0.0.1:{port}/ws{query}", max_queue=max_queue, additional_headers=headers,
                 open_timeout=10, max_size=None) as ws:  # fmt: skip
        ws.send(json.dumps({"op": "subscribe", "streams": list(streams)}))
        yield ws


def unpack(message) -> tuple[dict, bytes | None]:
    if isinstance(message, str):
        return json.loads(message), None
    (length,) = struct.unpack_from(">I", message)
    return json.loads(message[4 : 4 + length]), bytes(message[4 + length :])


def gradient(h=48, w=64) -> np.ndarray:
    yy, xx = np.mgrid[:h, :w]
    return np.stack([xx * 4, yy * 5, (xx + yy) * 2], axis=-1).clip(0, 255).astype(np.uint8)


def rendered(image, t=(0.0, 0.0, 3.0)) -> RenderedImage:
    return RenderedImage(image=image, K=K, R=np.eye(3), t=np.asarray(t, np.float64))


# --- the server alone -------------------------------------------------------------------------------------


def test_the_page_and_its_files_are_served_from_the_package_with_a_strict_policy():
    server = WebServer("127.0.0.1", 0)
    port = server.start()
    try:
        for path, kind in (("/", "text/html"), ("/avatar", "text/html"), ("/static/stg.js", "javascript")):
            code, headers, body = http(f"http://127.0.0.1:{port}{path}")
            assert code == 200 and kind in headers["Content-Type"] and body
            assert "default-src 'self'" in headers["Content-Security-Policy"]
        html = http(f"http://127.0.0.1:{port}/")[2].decode()
        assert "http://" not in html and "https://" not in html  # no CDN: every file is ours
        assert http(f"http://127.0.0.1:{port}/static/../web.py")[0] == 404
        assert http(f"http://127.0.0.1:{port}/nothing")[0] == 404
        stats = json.loads(http(f"http://127.0.0.1:{port}/stats.json")[2])
        assert stats == {"clients": [], "sent": 0, "drops": 0}
    finally:
        server.stop()


def test_a_token_is_required_beyond_this_machine_and_checked_everywhere(monkeypatch):
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.168.1.4")
    assert token_policy("127.0.0.1", {}) is None
    with pytest.raises(WebServerError, match="STG_WEB_TOKEN"):
        token_policy("0.0.0.0", {})
    with pytest.raises(WebServerError, match="at least 16"):
        token_policy("0.0.0.0", {"STG_WEB_TOKEN": "short"})
    assert token_policy("0.0.0.0", {"STG_WEB_TOKEN": TOKEN}) == TOKEN
    assert token_policy("127.0.0.1", {"STG_WEB_TOKEN": TOKEN}) == TOKEN  # set: required anyway

    server = WebServer("127.0.0.1", 0, token=TOKEN)
    port = server.start()
    try:
        base = f"http://127.0.0.1:{port}"
        assert http(f"{base}/")[0] == 401 and http(f"{base}/static/stg.js")[0] == 401
        assert http(f"{base}/?token=wrong-wrong-wrong-wrong")[0] == 401
        code, headers, _ = http(f"{base}/?token={TOKEN}")
        assert code == 200 and f"{TOKEN_COOKIE}={TOKEN}" in headers["Set-Cookie"]
        assert "HttpOnly" in headers["Set-Cookie"]
        cookie = {"Cookie": f"{TOKEN_COOKIE}={TOKEN}"}
        assert http(f"{base}/static/stg.js", cookie)[0] == 200  # the page's other files carry the cookie
        from websockets.exceptions import InvalidStatus

        with pytest.raises(InvalidStatus), page(port, ["status"]):
            pass
        with page(port, ["status"], headers=cookie) as ws:
            ws.send(json.dumps({"op": "ping", "t": 1.5}))
            pong, _ = unpack(ws.recv(timeout=10))
            assert pong["stream"] == "pong" and pong["t"] == 1.5
            assert abs(pong["server_ns"] - time.time_ns()) < 5e9
        with page(port, ["status"], query=f"?token={TOKEN}"):
            pass
    finally:
        server.stop()


def test_a_node_bound_beyond_this_machine_without_a_token_refuses_to_start(broker, bus_url, monkeypatch):
    monkeypatch.delenv("STG_WEB_TOKEN", raising=False)
    node = web_node(bus_url, host="0.0.0.0")
    with pytest.raises(NodeError, match="STG_WEB_TOKEN"):
        node.setup()
    node.close()


def test_the_steady_view_follows_a_repeating_camera_not_a_turning_one():
    steady = SteadyView(window_s=2.0)
    image = gradient()
    train = rendered(image)
    orbit = [rendered(image, t=(np.sin(a), 0.0, 3.0)) for a in np.linspace(0, 3, 12)]
    shown = []
    for i in range(12):  # the renderer's "both": train, orbit, train, orbit ...
        shown.append(("train", steady.accept(train, now=i * 0.1)))
        shown.append(("orbit", steady.accept(orbit[i], now=i * 0.1 + 0.05)))
    assert all(ok for name, ok in shown[2:] if name == "train")
    assert not any(ok for name, ok in shown[2:] if name == "orbit")
    only_orbit = SteadyView(window_s=2.0)  # nothing repeats: everything is shown
    assert all(only_orbit.accept(m, now=10 + i * 0.1) for i, m in enumerate(orbit))


# --- the node ---------------------------------------------------------------------------------------------


def test_a_page_gets_the_streams_it_asked_for_and_only_those_are_encoded(broker, bus_url, monkeypatch):
    encoded: list[tuple] = []
    real = web_module.encode_image

    def counting(image, *args, **kwargs):
        encoded.append(image.shape)
        return real(image, *args, **kwargs)

    monkeypatch.setattr(web_module, "encode_image", counting)
    node = web_node(bus_url)
    image = gradient()
    mask = np.zeros((48, 64), np.uint8)
    mask[10:30, 20:40] = 255
    with NodeThread(node), Bus(bus_url, node="renderer", heartbeat_s=0.2) as bus:
        assert wait_until(lambda: node.server is not None and node.server.port, timeout=20)
        for topic in ("avatar/image", "camera/frame"):
            assert bus.publisher.wait_for_subscribers(topic, 15)
        with page(node.server.port, ["avatar", "status"]) as ws:
            got: dict[str, list] = {}
            deadline = time.monotonic() + 60

            def renderer_seen() -> bool:  # a status that has heard the renderer's heartbeat
                return any("renderer" in meta["nodes"] for meta, _ in got.get("status", []))

            def read() -> None:
                with contextlib.suppress(TimeoutError):
                    meta, payload = unpack(ws.recv(timeout=0.3))
                    got.setdefault(meta["stream"], []).append((meta, payload))

            while not ("avatar" in got and renderer_seen()) and time.monotonic() < deadline:
                seq = bus.publish(rendered(image))
                bus.publish(Frame(index=0, image=image, mask=mask, K=K, R=np.eye(3), t=np.zeros(3)))
                read()

            # Publishing stopped: read on until the last image published arrives (the newest is
            # never superseded nor dropped; the node encodes in order): then every image encoded
            # for the page has reached it or been counted as a drop.
            def last_arrived() -> bool:
                return any(meta["seq"] == seq for meta, _ in got.get("avatar", []))

            deadline = time.monotonic() + 30
            while not last_arrived() and time.monotonic() < deadline:
                read()
    assert {"avatar", "status"} <= set(got) and "camera" not in got and "mask" not in got
    meta, jpeg = got["avatar"][-1]
    assert (meta["width"], meta["height"], meta["src"]) == (64, 48, "renderer") and 0 <= meta["seq"] <= seq
    assert abs(meta["stamp_ns"] - time.time_ns()) < 60e9
    decoded = cv2.cvtColor(cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    assert np.abs(decoded.astype(int) - image).mean() < 4
    status = [meta for meta, _ in got["status"] if "renderer" in meta["nodes"]][-1]
    assert status["nodes"]["renderer"]["state"] == "running" and status["web"]["clients"][0]["streams"] == [
        "avatar",
        "status",
    ]
    # Only the avatar was encoded, never the camera frames nobody watched.
    assert encoded and all(shape == (48, 64, 3) for shape in encoded)
    assert len(encoded) == sum(1 for m, _ in got["avatar"]) + node.server.drops


def noise(size: int) -> np.ndarray:
    return RNG.integers(0, 256, size=(size, size, 3), dtype=np.uint8)


def test_a_page_that_stops_reading_loses_frames_counted_and_slows_nobody(broker, bus_url):
    node = web_node(bus_url, jpeg_quality=95)
    frames = [noise(768) for _ in range(4)]  # ~1 MB JPEGs: a few fill a socket's buffers
    with NodeThread(node), Bus(bus_url, node="renderer", heartbeat_s=0.2) as bus:
        assert wait_until(lambda: node.server is not None and node.server.port, timeout=20)
        assert bus.publisher.wait_for_subscribers("avatar/image", 15)
        port = node.server.port
        with page(port, ["avatar"], max_queue=1), page(port, ["avatar"]) as healthy:  # the first never reads
            assert wait_until(lambda: len(node.server.clients) == 2, timeout=10)
            # The stalled page never reads again; the healthy one reads everything that comes.
            healthy_seen: list[int] = []
            deadline = time.monotonic() + 120
            i = 0
            stalled = min(node.server.clients.values(), key=lambda c: c.id)  # the first to connect

            while stalled.drops < 3 and time.monotonic() < deadline:
                bus.publish(rendered(frames[i % 4]))
                i += 1
                with contextlib.suppress(TimeoutError):
                    while True:
                        healthy_seen.append(unpack(healthy.recv(timeout=0.05))[0]["seq"])
            assert stalled.drops >= 3 and stalled.sent < len(healthy_seen)
            # With the stalled page connected and silent, fresh frames keep reaching the other.
            fresh_from = bus.publish(rendered(frames[0]))
            newer: list[int] = []
            deadline = time.monotonic() + 60
            while len(newer) < 5 and time.monotonic() < deadline:
                bus.publish(rendered(frames[1]))
                with contextlib.suppress(TimeoutError):
                    seq = unpack(healthy.recv(timeout=0.5))[0]["seq"]
                    if seq >= fresh_from:
                        newer.append(seq)
            assert len(newer) >= 5 and newer == sorted(newer)
            # Counted where an operator looks: the node's NodeStatus drops.
            assert wait_until(lambda: node.heartbeat.traffic.snapshot()["drops"].get("slow_client", 0) >= 3)


def test_the_skeleton_is_the_poses_joints_seen_by_the_camera_of_its_own_frame(broker, bus_url):
    node = web_node(bus_url, camera_max_side=32)  # 64 x 48 frames are sent at 32 x 24
    joints = (RNG.normal(size=(24, 3)) * 0.3 + [0.0, 0.0, 3.0]).astype(np.float32)
    rvec, t = np.array([0.05, -0.1, 0.02]), np.array([0.1, 0.0, 0.2])
    R = cv2.Rodrigues(rvec)[0]
    with NodeThread(node), Bus(bus_url, node="pipeline", heartbeat_s=0) as bus:
        assert wait_until(lambda: node.server is not None and node.server.port, timeout=20)
        for topic in ("camera/frame", "body/pose"):
            assert bus.publisher.wait_for_subscribers(topic, 15)
        with page(node.server.port, ["camera", "skeleton"]) as ws:
            # a round that times out under load leaves its skeleton in flight: the next round's
            # camera frame may arrive before it, so a skeleton is matched to the camera frame of
            # its own frame_seq, whichever round sent them
            skeleton = camera = None
            cameras: dict[int, dict] = {}
            deadline = time.monotonic() + 60
            while skeleton is None and time.monotonic() < deadline:
                seq = bus.publish(Frame(index=3, image=gradient(), K=K, R=R, t=t))
                other = bus.publish(Frame(index=3, image=gradient(), K=K, R=np.eye(3), t=np.zeros(3)))
                pose = BodyPose(poses=np.zeros((24, 3), np.float32), Rh=np.zeros(3, np.float32),
                                Th=np.zeros(3, np.float32), betas=np.zeros(10, np.float32), joints=joints,
                                frame_seq=seq, frame_index=3)  # fmt: skip
                bus.publish(pose)
                with contextlib.suppress(TimeoutError):
                    while True:
                        meta, _ = unpack(ws.recv(timeout=0.3))
                        if meta["stream"] == "camera":
                            cameras[meta["seq"]] = meta
                        if meta["stream"] == "skeleton" and meta["frame_seq"] in cameras:
                            skeleton, camera = meta, cameras[meta["frame_seq"]]
                            break
    assert skeleton is not None and other > seq
    assert skeleton["frame_seq"] == camera["seq"] and (skeleton["width"], skeleton["height"]) == (32, 24)
    want, _ = cv2.projectPoints(joints.astype(np.float64), rvec, t, K, None)
    np.testing.assert_allclose(np.array(skeleton["points"]), want.reshape(-1, 2) * 0.5, atol=0.06)
    assert skeleton["parents"][:4] == [-1, 0, 0, 0]
