"""Lockstep acknowledgements: nodes asked to (``ack``) publish an Ack naming each message they have
finished with, and ``stg-bag play --lockstep`` (the library Player) waits for it.

The truth: the order in which the node's own output and its Acks reach an independent
subscriber (the Ack comes after what the handler published), the Acks' contents against the
recorded headers, and the trainer's exact iteration count."""

from __future__ import annotations

import logging
import threading
import time

import numpy as np
import pytest
from fake_avatar import TrainConfig, Trainer
from nodehelpers import NodeThread, wait_until
from sample_nodes import Echo, EchoParams, pose

from stg_node.bus import Bus, BusConfig, Frame, Subscriber, ViewRequest
from stg_node.bus.recording import BagReader, BagWriter, Lockstep, PlaybackError, Player
from stg_node.launch.spec import read_launch
from stg_node.launch.yamlfile import LaunchFileError
from stg_node.nodes.params import parse_params
from stg_node.nodes.renderer import RendererNode, RendererParams
from stg_node.nodes.trainer import TrainerNode, TrainerParams

FAKE = "tests.nodes.fake_avatar"
T0 = 10**18
K = np.array([[100.0, 0, 32], [0, 100.0, 32], [0, 0, 1]])


def frame(index: int) -> Frame:
    image = np.full((8, 8, 3), 100 + index, np.uint8)
    return Frame(
        index=index,
        image=image,
        mask=np.full((8, 8), 255, np.uint8),
        K=np.eye(3),
        R=np.eye(3),
        t=np.array([0.0, 0.0, 3.0]),
    )


def training_session(path, count: int) -> None:
    """``count`` frames, each followed by its pose (frame_seq set), as ingest and tracker send them."""
    with BagWriter(path) as bag:
        t = T0
        for i in range(count):
            seq = bag.write_message(frame(i), t, src="ingest")
            p = pose(i)
            p.frame_seq = seq
            bag.write_message(p, t + 1000, src="tracker")
            t += 10**8


def play(path, bus_url, lockstep: Lockstep) -> object:
    return Player(BagReader(path), config=BusConfig(url=bus_url), rate=0, lockstep=lockstep).run()


def lockstep_run(node, path, bus_url, watch: list[str], expect: int):
    """Play ``path`` in lockstep into ``node`` (running in a thread); the player's stats and the
    messages on ``watch`` in the order an independent subscriber received them (``expect`` of them,
    and whatever else came within half a second)."""
    seen: list = []
    done = threading.Event()

    def receive(sub):
        while not done.is_set():
            msg = sub.recv(timeout=0.05)
            if msg is not None:
                seen.append(msg)

    with Subscriber(BusConfig(url=bus_url), watch, keep_last=False) as sub:
        # The watcher's subscriptions must be through the broker before anything is played: the
        # node answers within milliseconds, and PUB/SUB drops what nobody had subscribed to yet.
        with Bus(bus_url, node="probe", heartbeat_s=0) as probe:
            for topic in watch:
                assert probe.publisher.wait_for_subscribers(topic, 60), topic
        receiver = threading.Thread(target=receive, args=(sub,), daemon=True)
        receiver.start()
        try:
            with NodeThread(node):
                stats = play(path, bus_url, Lockstep(timeout_s=60))
                assert wait_until(lambda: len(seen) >= expect, 60), seen
                time.sleep(0.5)  # anything beyond what was expected (a step too many) would show now
        finally:
            done.set()
            receiver.join()
    return stats, seen


def test_a_hooks_node_acknowledges_each_message_after_its_handler_returned(broker, bus_url, tmp_path):
    path = tmp_path / "poses.mcap"
    with BagWriter(path) as bag:
        for i in range(6):
            bag.write_message(pose(i), T0 + i * 10**7, src="tracker")
    echo = Echo("echo", EchoParams(), BusConfig(url=bus_url), heartbeat_s=0, ack=["body/pose"])
    stats, seen = lockstep_run(echo, path, bus_url, ["trainer/metrics", "node/ack"], 12)
    assert (stats.published, stats.acks, stats.stray_acks) == (6, 6, 0)
    # Echo publishes a metrics message per pose in its handler; the runtime acks after it returns
    kinds = [(type(m).__name__, m.iteration if hasattr(m, "iteration") else m.msg_seq) for m in seen]
    assert kinds == [x for i in range(6) for x in (("TrainerMetrics", i), ("Ack", i))]
    acks = [m for m in seen if type(m).__name__ == "Ack"]
    assert {(a.msg_topic, a.msg_src, a.header.src) for a in acks} == {("body/pose", "tracker", "echo")}
    assert echo.acks_sent == 6


def test_without_acknowledgements_lockstep_fails_in_time_and_names_the_message(broker, bus_url, tmp_path):
    path = tmp_path / "poses.mcap"
    with BagWriter(path) as bag:
        bag.write_message(pose(0), T0, src="tracker")
    with NodeThread(Echo("echo", EchoParams(), BusConfig(url=bus_url), heartbeat_s=0)):
        with pytest.raises(PlaybackError, match=r"0 of 1 acknowledgement.*body/pose seq 0 from tracker"):
            play(path, bus_url, Lockstep(timeout_s=1.0))


def test_acking_a_topic_the_node_does_not_subscribe_is_reported(broker, bus_url, caplog):
    echo = Echo("echo", EchoParams(), BusConfig(url=bus_url), heartbeat_s=0, ack=["camera/frame"])
    with caplog.at_level(logging.WARNING, logger="stg_node.nodes.echo"), NodeThread(echo):
        assert wait_until(lambda: "does not subscribe 'camera/frame'" in caplog.text, 30)
    assert echo.acks("body/pose") is False and echo.acks("camera/frame") is True
    star = Echo("star", EchoParams(), BusConfig(url=bus_url), heartbeat_s=0, ack=["*"])
    star.subscribe("body/pose")
    assert star.acks("body/pose") and not star.acks("camera/frame")
    star.bus.close()


def test_trainer_steps_exactly_n_times_per_frame_under_lockstep(broker, bus_url, tmp_path):
    path = tmp_path / "session.mcap"
    training_session(path, 5)
    params = parse_params(
        TrainerParams,
        {"avatar": FAKE, "steps_per_frame": 3, "snapshot_every_s": 0, "checkpoint_every_s": 0},
    )
    node = TrainerNode(
        "trainer", params, BusConfig(url=bus_url), heartbeat_s=0, ack=["camera/frame", "body/pose"]
    )
    stats, seen = lockstep_run(node, path, bus_url, ["trainer/metrics", "node/ack"], 5 * 3 + 10)
    assert (stats.published, stats.acks, stats.stray_acks) == (10, 10, 0)
    # each frame is acknowledged when stored (its pose is still to come); each pose after the three
    # steps it brought, whose metrics precede its Ack
    order = [
        ("M", m.iteration) if type(m).__name__ == "TrainerMetrics" else (m.msg_topic, m.msg_seq) for m in seen
    ]
    expected = []
    for i in range(5):
        expected += [
            ("camera/frame", i),
            ("M", 3 * i + 1),
            ("M", 3 * i + 2),
            ("M", 3 * i + 3),
            ("body/pose", i),
        ]
    assert order == expected
    assert node.iteration == 15 and node.frames_added == 5  # and no step more while it waited


def test_renderer_acknowledges_a_view_request_after_publishing_its_image(broker, bus_url, tmp_path):
    snap = Trainer(TrainConfig()).snapshot()
    snap.arrays["color"] = np.array([[0.2, 0.4, 0.6]], np.float32)
    snap.model_version = 4
    path = tmp_path / "views.mcap"
    with BagWriter(path) as bag:
        bag.write_message(snap, T0, src="trainer")
        for i in range(3):
            view = ViewRequest(
                request_id=i,
                width=64,
                height=64,
                follow_live=False,
                K=K,
                R=np.eye(3),
                t=np.array([0.0, 0.0, 3.0]),
                poses=np.zeros((24, 3), np.float32),
                Th=np.array([0.1 * i, 0.0, 0.0], np.float32),
            )
            bag.write_message(view, T0 + (i + 1) * 10**7, src="robot")
    params = parse_params(RendererParams, {"avatar": FAKE, "default_view": "none", "idle_rate_hz": 0})
    node = RendererNode(
        "renderer", params, BusConfig(url=bus_url), heartbeat_s=0, ack=["avatar/view", "avatar/snapshot"]
    )
    stats, seen = lockstep_run(node, path, bus_url, ["avatar/image", "node/ack"], 7)
    assert (stats.published, stats.acks, stats.stray_acks) == (4, 4, 0)
    images = {m.request_id: m for m in seen if type(m).__name__ == "RenderedImage"}
    acks = [m for m in seen if type(m).__name__ == "Ack"]
    assert [(a.msg_topic, a.msg_seq) for a in acks] == [("avatar/snapshot", 0)] + [
        ("avatar/view", i) for i in range(3)
    ]
    assert sorted(images) == [0, 1, 2]
    assert {m.snapshot_version for m in images.values()} == {4}  # the snapshot was in before the views
    # images and Acks travel on different lanes (sockets), so their arrival order proves nothing;
    # their stamps, taken by the node when it published each, do: every Ack after its image
    for ack in acks[1:]:
        assert ack.header.stamp_ns >= images[ack.msg_seq].header.stamp_ns


def test_launch_files_pass_ack_to_kind_nodes_only(tmp_path):
    good = tmp_path / "good.yaml"
    good.write_text(
        "nodes:\n"
        "  - {name: t, kind: trainer, params: {avatar: tests.nodes.fake_avatar},\n"
        "     ack: [camera/frame, body/pose]}\n"
    )
    spec = read_launch(good)
    cmd = spec.nodes[0].command(spec.bus)
    assert cmd[cmd.index("--ack") :][:4] == ["--ack", "camera/frame", "--ack", "body/pose"]
    bad = tmp_path / "bad.yaml"
    bad.write_text("nodes:\n  - name: p\n    cmd: [sleep, '1']\n    ack: [node/ack]\n")
    with pytest.raises(LaunchFileError, match=r"bad.yaml:4: .*ack is for kind nodes"):
        read_launch(bad)
