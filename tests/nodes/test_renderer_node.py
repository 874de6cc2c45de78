"""The renderer node on a fake avatar: default and requested views, latency fields, hot swaps."""

from __future__ import annotations

import importlib
import time

import numpy as np
import pytest
from fake_avatar import BODY_RADIUS_M, TrainConfig, Trainer, project
from nodehelpers import NodeThread, recv_until, wait_until
from sample_nodes import pose

from stg_node.bus import Bus, BusConfig, Frame, Subscriber, ViewRequest
from stg_node.bus.messages import NodeStatus, RenderedImage
from stg_node.data.types import Camera
from stg_node.nodes.params import parse_params
from stg_node.nodes.renderer import RendererNode, RendererParams
from stg_node.nodes.views import orbit_camera

FAKE = "tests.nodes.fake_avatar"
K = np.array([[100.0, 0, 32], [0, 100.0, 32], [0, 0, 1]])


def renderer(bus_url, **params) -> RendererNode:
    values = {"avatar": FAKE, "idle_rate_hz": 20, "default_view": "train", "size": 64, **params}
    return RendererNode(
        "renderer", parse_params(RendererParams, values), BusConfig(url=bus_url), heartbeat_s=0.1
    )


def snapshot(iteration: int, color=(0.2, 0.4, 0.6), load_s: float = 0.0):
    trainer = Trainer(TrainConfig(load_s=load_s))
    trainer.iteration = iteration
    msg = trainer.snapshot()
    msg.arrays["color"] = np.array([color], np.float32)
    msg.model_version = iteration
    return msg


def body_at(th) -> object:
    p = pose(5)
    p.Th = np.asarray(th, np.float32)
    return p


def train_frame() -> Frame:
    return Frame(
        index=0, image=np.zeros((64, 64, 3), np.uint8), K=K, R=np.eye(3), t=np.array([0.0, 0.0, 3.0])
    )


def wait_subscribed(bus: Bus, *topics: str) -> None:
    for topic in topics:
        assert bus.publisher.wait_for_subscribers(topic, 15), topic


def disc_center(image: RenderedImage) -> tuple[float, float]:
    ys, xs = np.nonzero(image.alpha)
    return xs.mean() + 0.5, ys.mean() + 0.5


def test_default_view_renders_the_live_pose_from_the_training_camera(broker, bus_url):
    node = renderer(bus_url)
    with Subscriber(BusConfig(url=bus_url), ["avatar/image"]) as images, NodeThread(node):
        with Bus(bus_url, node="pipeline", heartbeat_s=0) as bus:
            wait_subscribed(bus, "avatar/snapshot", "body/pose", "camera/frame")
            bus.publish(snapshot(3))
            bus.publish(train_frame())
            assert wait_until(lambda: node.train_camera is not None, 30)  # the view it renders from
            stamp = time.time_ns()
            seq = bus.publish(body_at([0.1, -0.05, 0.0]), stamp_ns=stamp)
            got = recv_until(images, lambda m: m.pose_seq == seq, 30)
            received = time.time_ns()
    assert got is not None and got.pose_seq == seq
    assert got.snapshot_version == 3 and got.request_id == -1
    u, v, depth = project(
        Camera(K=K, R=np.eye(3), t=np.array([0, 0, 3.0]), width=64, height=64), [0.1, -0.05, 0]
    )
    cu, cv = disc_center(got)
    assert (cu, cv) == pytest.approx((u, v), abs=0.6)  # independent: the pinhole projection of the body root
    assert (got.alpha > 0).sum() == pytest.approx(np.pi * (100 * BODY_RADIUS_M / depth) ** 2, rel=0.15)
    np.testing.assert_allclose(got.image[int(cv), int(cu)], [51, 102, 153], atol=1)
    # latency: from the pose's stamp to the image's publication, so within what the test saw
    assert got.source_stamp_ns == stamp and 0 <= got.latency_ms <= (received - stamp) / 1e6
    assert got.render_ms > 0


def test_one_shot_and_standing_view_requests(broker, bus_url):
    node = renderer(bus_url, idle_rate_hz=10)
    R = orbit_camera(
        Camera(K=K, R=np.eye(3), t=np.array([0, 0, 3.0]), width=64, height=64), np.zeros(3), 0.3
    ).R
    K2 = np.array([[100.0, 0, 24], [0, 100.0, 20], [0, 0, 1]])
    oneshot = ViewRequest(
        request_id=42,
        width=48,
        height=40,
        follow_live=False,
        K=K2,
        R=R,
        t=np.array([0, 0, 2.0]),
        poses=np.zeros((24, 3), np.float32),
        Th=np.array([0.05, 0.0, 0.2], np.float32),
    )
    standing = ViewRequest(
        request_id=7, width=32, height=32, follow_live=True, K=K, R=np.eye(3), t=np.array([0, 0, 4.0])
    )
    with Subscriber(BusConfig(url=bus_url), ["avatar/image"], keep_last=False) as images, NodeThread(node):
        with Bus(bus_url, node="robot", heartbeat_s=0) as robot:
            wait_subscribed(robot, "avatar/snapshot", "avatar/view", "body/pose")
            robot.publish(snapshot(1))
            robot.publish(body_at([0, 0, 0]))
            stamp = time.time_ns()
            robot.publish(oneshot, stamp_ns=stamp)
            shot = recv_until(images, lambda m: m.request_id == 42, 30)
            received = time.time_ns()
            robot.publish(standing)
            first = recv_until(images, lambda m: m.request_id == 7, 30)
            # with a standing view, no default views any more: what follows its first image (in
            # order, on one socket) is for it alone
            later, deadline = [], time.monotonic() + 1.0
            while time.monotonic() < deadline:
                if (msg := images.recv(timeout=0.1)) is not None:
                    later.append(msg.request_id)
    assert shot is not None and first is not None
    assert later and set(later) == {7}, later
    assert shot.image.shape == (40, 48, 3) and shot.request_src == "robot" and shot.pose_seq == -1
    assert shot.source_stamp_ns == stamp and 0 <= shot.latency_ms <= (received - stamp) / 1e6
    u, v, _ = project(Camera(K=K2, R=R, t=np.array([0, 0, 2.0]), width=48, height=40), [0.05, 0, 0.2])
    assert 12 < u < 36 and 8 < v < 32  # the disc lies inside the image
    assert disc_center(shot) == pytest.approx((u, v), abs=0.6)
    np.testing.assert_allclose(shot.R, R)
    assert first.image.shape == (32, 32, 3)


def test_snapshots_are_swapped_without_a_pause_and_bad_ones_are_refused(broker, bus_url):
    """A snapshot that takes long to load (held open by the fake avatar's gate for as long as the
    test needs) does not stop the renderer: the old one keeps rendering until the new one is in.
    How long the pause is at the swap is a timing, measured by tools/bench_pipeline.py (swap)."""
    gate = importlib.import_module(FAKE).LOAD_GATE  # the module instance the node loaded
    gate.clear()
    node = renderer(bus_url, idle_rate_hz=50, max_rate_hz=50)
    with (
        Subscriber(BusConfig(url=bus_url), ["avatar/image", "node/status"], keep_last=False) as sub,
        NodeThread(node),
    ):
        with Bus(bus_url, node="trainer", heartbeat_s=0) as trainer:
            wait_subscribed(trainer, "avatar/snapshot", "body/pose")
            trainer.publish(snapshot(1, color=(1.0, 0.0, 0.0)))
            trainer.publish(body_at([0, 0, 0]))
            versions = []  # snapshot version of each image, in order
            drops = {}

            def until(predicate, timeout=30.0):
                deadline = time.monotonic() + timeout
                while time.monotonic() < deadline:
                    msg = sub.recv(timeout=0.1)
                    if isinstance(msg, RenderedImage):
                        versions.append(msg.snapshot_version)
                    elif isinstance(msg, NodeStatus) and msg.node == "renderer":
                        drops.update(msg.drops)
                    if predicate():
                        return True
                return False

            try:
                assert until(lambda: len(versions) > 3)
                slow = snapshot(2, color=(0.0, 1.0, 0.0))
                slow.meta["gate"] = 1.0
                trainer.publish(slow)
                assert wait_until(lambda: node.loader.loading, 30)  # the load is under way ...
                loading_from = len(versions)
                assert until(lambda: len(versions) >= loading_from + 10)  # ... and images keep coming
                assert node.loader.loading  # (still loading: the gate holds it)
            finally:
                gate.set()
            assert until(lambda: versions[-1] == 2)
            bad = snapshot(3)
            bad.format = "other/9"
            trainer.publish(bad)
            assert until(lambda: drops.get("bad_snapshot") == 1)
            swapped = len(versions)
            assert until(lambda: len(versions) > swapped + 3)
    during = versions[loading_from : loading_from + 10]
    assert during == [1] * 10  # the old snapshot kept rendering through the load
    assert versions[swapped:] and set(versions[swapped:]) == {2}  # the bad one was not swapped in


def test_the_renderer_keeps_serving_when_the_trainer_is_gone_and_on_a_late_start(broker, bus_url):
    """The broker latches the snapshot: a renderer (re)started later renders at once. (The broker
    latches what reaches it, i.e. what someone subscribed to when it was published: here a
    previous renderer.)"""
    with (
        Subscriber(BusConfig(url=bus_url), ["avatar/snapshot"]),
        Bus(bus_url, node="trainer", heartbeat_s=0) as trainer,
    ):
        wait_subscribed(trainer, "avatar/snapshot")
        trainer.publish(snapshot(9))
        assert wait_until(lambda: b"avatar/snapshot" in broker.cache, 30)  # before the trainer goes
    node = renderer(bus_url)  # the trainer is gone now
    with Subscriber(BusConfig(url=bus_url), ["avatar/image"]) as images, NodeThread(node):
        with Bus(bus_url, node="tracker", heartbeat_s=0) as tracker:
            wait_subscribed(tracker, "body/pose")
            tracker.publish(body_at([0, 0, 0]))
            got = [images.recv(timeout=30) for _ in range(3)]
    assert all(g is not None and g.snapshot_version == 9 for g in got), got


def test_the_default_orbit_view_frames_the_body_whatever_the_training_distance(broker, bus_url):
    """The orbit view aims at the body and makes it about 2/3 of the image tall (stg-render's
    rule), with the training camera 3 m or 30 m away: the fake avatar is a 0.5 m sphere."""
    for distance in (3.0, 30.0):
        node = renderer(bus_url, default_view="orbit", orbit_period_s=2.0)
        frame = train_frame()
        frame.t = np.array([0.0, 0.0, distance])
        with Subscriber(BusConfig(url=bus_url), ["avatar/image"]) as images, NodeThread(node):
            with Bus(bus_url, node="pipeline", heartbeat_s=0) as bus:
                wait_subscribed(bus, "avatar/snapshot", "body/pose", "camera/frame")
                bus.publish(snapshot(3))
                bus.publish(frame)
                # the training camera (the distance the orbit starts from) has arrived
                assert wait_until(lambda n=node: n.train_camera is not None, 30)
                got = []
                deadline = time.monotonic() + 20
                while time.monotonic() < deadline and len(got) < 6:
                    bus.publish(body_at([0.3, -0.2, 0.5]))
                    image = images.recv(timeout=1)
                    if image is not None and image.alpha.any():
                        got.append(image)
        assert len(got) == 6, distance
        for image in got[2:]:  # after the smoothing has settled
            ys, xs = np.nonzero(image.alpha)
            assert (ys.max() - ys.min() + 1) / 64 == pytest.approx(2 / 3, abs=0.08), distance
            assert disc_center(image) == pytest.approx((32.0, 32.0), abs=2.0), distance


def test_the_contact_sheet_shows_the_last_snapshot_from_the_training_camera_and_an_orbit(
    broker, bus_url, tmp_path
):
    """The sheet is the final model (not the first, untrained one) in 12 views; the MP4 has everything."""
    import cv2

    early, late = (0.9, 0.1, 0.1), (0.1, 0.9, 0.1)
    node = renderer(bus_url, default_view="both", record_dir=str(tmp_path), idle_rate_hz=20)
    with Subscriber(BusConfig(url=bus_url), ["avatar/image"]) as images, NodeThread(node) as thread:
        with Bus(bus_url, node="pipeline", heartbeat_s=0) as bus:
            wait_subscribed(bus, "avatar/snapshot", "body/pose", "camera/frame")
            bus.publish(train_frame())
            for version, color in ((1, early), (7, late)):
                bus.publish(snapshot(version, color))
                deadline = time.monotonic() + 10
                got = None
                while time.monotonic() < deadline and (got is None or got.snapshot_version != version):
                    bus.publish(body_at([0.0, 0.0, 0.0]))
                    got = images.recv(timeout=1)
                assert got is not None and got.snapshot_version == version
        assert thread.stop() == 0
    sheet = cv2.cvtColor(cv2.imread(str(tmp_path / "avatar_sheet.png")), cv2.COLOR_BGR2RGB)
    assert sheet.shape == (3 * 192, 4 * 192, 3)
    late_rgb = np.rint(np.array(late) * 255)
    early_rgb = np.rint(np.array(early) * 255)
    for r in range(3):
        for c in range(4):
            tile = sheet[r * 192 : (r + 1) * 192, c * 192 : (c + 1) * 192].reshape(-1, 3).astype(float)
            assert (np.abs(tile - late_rgb).max(axis=1) < 40).sum() > 50, (r, c)
            assert (np.abs(tile - early_rgb).max(axis=1) < 40).sum() == 0, (r, c)
    assert (tmp_path / "avatar.mp4").stat().st_size > 0


def test_orbit_keeps_distance_and_height_and_looks_at_the_body():
    train = Camera(K=K, R=np.eye(3), t=np.array([0.0, 0.0, 3.0]), width=64, height=64)
    center = np.array([0.2, 0.0, 0.0])
    for angle in np.linspace(0, 2 * np.pi, 7):
        cam = orbit_camera(train, center, angle)
        position = -cam.R.T @ cam.t
        assert np.linalg.norm(position - center) == pytest.approx(
            np.linalg.norm(np.array([0, 0, -3.0]) - center)
        )
        assert position[1] == pytest.approx(0.0, abs=1e-9)  # height along the image's up axis kept
        np.testing.assert_allclose(cam.R @ cam.R.T, np.eye(3), atol=1e-12)
        u, v, _ = project(cam, center)
        assert (u, v) == pytest.approx(project(train, center)[:2], abs=1e-6)
