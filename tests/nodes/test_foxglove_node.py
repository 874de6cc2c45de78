"""The foxglove node seen through a raw client of the Foxglove WebSocket protocol (foxglove_client:
websockets + JSON + protobuf from the advertised schemas): what it serves, that it encodes only
what a client watches, and that a client that stops reading costs the others nothing while the
node counts what it dropped."""

from __future__ import annotations

import socket
import threading
import time

import cv2
import numpy as np
from fake_avatar import BODY_RADIUS_M, POINTS, TrainConfig, Trainer
from foxglove_client import FoxgloveClient
from nodehelpers import NodeThread, child_env, spawn, wait_until

from stg_node.body.smpl_io import SMPL_PARENTS
from stg_node.bus import BodyPose, Bus, BusConfig, Frame, NodeStatus, RenderedImage, Subscriber
from stg_node.nodes.foxglove_bridge import FoxgloveNode, FoxgloveParams
from stg_node.nodes.params import parse_params

FAKE = "tests.nodes.fake_avatar"
K = np.array([[80.0, 0, 32], [0, 80.0, 24], [0, 0, 1]])
RNG = np.random.default_rng(5)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def foxglove_node(bus_url, **params) -> FoxgloveNode:
    values = {"port": free_port(), "avatar": FAKE, "cloud_rate_hz": 20.0, **params}
    return FoxgloveNode(
        "foxglove", parse_params(FoxgloveParams, values), BusConfig(url=bus_url), heartbeat_s=0.2
    )


def gradient(h=48, w=64) -> np.ndarray:
    yy, xx = np.mgrid[:h, :w]
    return np.stack([xx * 4, yy * 5, (xx + yy) * 2], axis=-1).clip(0, 255).astype(np.uint8)


def body(joints=None) -> BodyPose:
    return BodyPose(
        poses=np.zeros((24, 3), np.float32),
        Rh=np.zeros(3, np.float32),
        Th=np.array([0.2, -0.1, 0.5], np.float32),
        betas=np.zeros(10, np.float32),
        joints=joints,
    )


COLOR = (0.1, 0.6, 0.3)


def snapshot(color=COLOR):
    msg = Trainer(TrainConfig()).snapshot()
    msg.arrays["color"] = np.array([color], np.float32)
    msg.model_version = 4
    return msg


def decode_points(cloud) -> np.ndarray:
    """(N, 7) x, y, z, r, g, b, a from a foxglove.PointCloud, read by the fields it declares."""
    names = {"x": "<f4", "y": "<f4", "z": "<f4", "red": "u1", "green": "u1", "blue": "u1", "alpha": "u1"}
    fields = {f.name: f.offset for f in cloud.fields}
    assert set(fields) == set(names)
    dtype = np.dtype({"names": list(names), "formats": list(names.values()),
                      "offsets": [fields[n] for n in names], "itemsize": cloud.point_stride})  # fmt: skip
    raw = np.frombuffer(cloud.data, dtype)
    return np.stack([raw[n].astype(np.float64) for n in names], axis=1)


def test_it_serves_views_in_foxglove_schemas_and_encodes_only_what_is_watched(broker, bus_url):
    node = foxglove_node(bus_url)
    watched = ["view/avatar/image/image", "view/body/pose/skeleton", "view/avatar/snapshot/cloud"]
    with NodeThread(node), Bus(bus_url, node="pipeline", heartbeat_s=0) as bus:
        assert wait_until(lambda: node.server is not None, timeout=20)
        with FoxgloveClient(f"ws://127.0.0.1:{node.server.port}") as client:
            client.wait_for_channels(watched + ["view/camera/frame/image"])
            schemas = {t: c["schemaName"] for t, c in client.channels.items()}
            assert schemas["view/camera/frame/calibration"] == "foxglove.CameraCalibration"
            assert schemas["view/body/pose/skeleton"] == "foxglove.SceneUpdate"
            assert schemas["view/avatar/snapshot/cloud"] == "foxglove.PointCloud"
            assert schemas["view/trainer/metrics/fields"] == "stg.TrainerMetrics fields"
            client.subscribe(*watched)
            for topic in ("avatar/image", "body/pose", "avatar/snapshot", "camera/frame"):
                assert bus.publisher.wait_for_subscribers(topic, 15), topic
            joints = RNG.normal(size=(24, 3)).astype(np.float32)
            image = gradient()
            bus.publish(snapshot())
            got: dict[str, object] = {}
            deadline = time.monotonic() + 60
            while set(got) != set(watched) and time.monotonic() < deadline:
                bus.publish(RenderedImage(image=image, K=K, R=np.eye(3), t=np.zeros(3)))
                bus.publish(Frame(index=0, image=image, K=K, R=np.eye(3), t=np.zeros(3)))
                bus.publish(body(joints))
                try:
                    received = client.receive(timeout=0.5)
                except TimeoutError:
                    continue
                got[received.topic] = received.message
    assert set(got) == set(watched), sorted(got)
    # The avatar: a JPEG of the image published.
    jpeg = got["view/avatar/image/image"]
    decoded = cv2.cvtColor(
        cv2.imdecode(np.frombuffer(jpeg.data, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB
    )
    assert jpeg.format == "jpeg" and np.abs(decoded.astype(int) - image).mean() < 4
    # The skeleton: a sphere on every joint, a bone from each joint to its parent, in the world.
    entity = got["view/body/pose/skeleton"].entities[0]
    assert entity.frame_id == "world"
    centres = np.array([[s.pose.position.x, s.pose.position.y, s.pose.position.z] for s in entity.spheres])
    np.testing.assert_allclose(centres, joints, atol=1e-6)
    ends = np.array([[p.x, p.y, p.z] for p in entity.lines[0].points]).reshape(-1, 2, 3)
    want = np.array([[joints[p], joints[c]] for c, p in enumerate(SMPL_PARENTS) if p >= 0])
    np.testing.assert_allclose(ends, want, atol=1e-6)
    # The point cloud: the fake avatar's ring of points around the root, in the snapshot's colour.
    points = decode_points(got["view/avatar/snapshot/cloud"])
    assert len(points) == POINTS
    radius = np.linalg.norm(points[:, :3] - body().Th, axis=1)
    np.testing.assert_allclose(radius, BODY_RADIUS_M, atol=1e-5)
    rgb = np.rint(np.array(COLOR, np.float32) * 255)  # as the fake avatar rounds it
    np.testing.assert_array_equal(points[:, 3:], np.tile([*rgb, 255], (POINTS, 1)))
    # Nothing watched the camera: it was never encoded, though frames kept coming.
    assert node.sent.get("view/camera/frame/image", 0) == 0 and node.sent["view/avatar/image/image"] >= 1


def noise_image(size: int) -> RenderedImage:
    """A large image JPEG hardly compresses: a few of them fill a socket's buffers."""
    image = RNG.integers(0, 256, size=(size, size, 3), dtype=np.uint8)
    return RenderedImage(image=image, K=K, R=np.eye(3), t=np.zeros(3))


def test_a_client_that_stops_reading_costs_others_nothing_and_drops_are_counted(broker, bus_url):
    """The node in its own process (the SDK's overflow report is once per 30 s per process), fed
    large images; one client subscribes and never reads again, another keeps reading."""
    port = free_port()
    node = spawn(
        ["-m", "stg_node.nodes", "foxglove", "--port", str(port), "--bus", bus_url, "--heartbeat", "0.2",
         "--param", "backlog=4", "--param", "topics=[\"avatar/image\"]"],
        env=child_env(),
    )  # fmt: skip
    output: list[str] = []
    threading.Thread(target=lambda: output.extend(iter(node.stdout.readline, "")), daemon=True).start()
    statuses: list[NodeStatus] = []
    try:
        with Subscriber(BusConfig(url=bus_url), ["node/status"]) as sub, Bus(bus_url, node="renderer") as bus:

            def status() -> NodeStatus | None:
                """The node's latest NodeStatus (reading what came since)."""
                while (msg := sub.recv(timeout=0)) is not None:
                    if msg.node == "foxglove":
                        statuses.append(msg)
                return statuses[-1] if statuses else None

            stalled = FoxgloveClient(f"ws://127.0.0.1:{port}", max_queue=1, timeout=60)
            healthy = FoxgloveClient(f"ws://127.0.0.1:{port}", timeout=60)
            for client in (stalled, healthy):
                client.wait_for_channels(["view/avatar/image/image"])
                client.subscribe("view/avatar/image/image")
            assert bus.publisher.wait_for_subscribers("avatar/image", 30)

            def dropped() -> int:
                return status().drops.get("client_backlog", 0) if status() else 0

            # The stalled client never reads again; the healthy one reads all along, until the
            # stalled one's outbox overflowed and the node counted it.
            deadline = time.monotonic() + 120
            while dropped() < 1 and time.monotonic() < deadline:
                bus.publish(noise_image(768))
                while True:
                    try:
                        healthy.receive(timeout=0.05)
                    except TimeoutError:
                        break
            assert dropped() >= 1, "".join(output)[-3000:]
            taken = status().received.get("avatar/image", 0)
            # The stalled client still connected and silent: new images keep reaching the other, and
            # the node keeps taking every image the bus brings.
            fresh = []
            deadline = time.monotonic() + 60
            while len(fresh) < 5 and time.monotonic() < deadline:
                bus.publish(noise_image(768))
                try:
                    fresh.append(healthy.receive(timeout=1.0))
                except TimeoutError:
                    continue
            assert len(fresh) >= 5, "".join(output)[-3000:]
            assert wait_until(lambda: status().received.get("avatar/image", 0) >= taken + 5, timeout=30)
            stalled.close()
            healthy.close()
    finally:
        node.send_signal(2)
        node.wait(timeout=30)
    assert node.returncode == 0, "".join(output)[-3000:]
