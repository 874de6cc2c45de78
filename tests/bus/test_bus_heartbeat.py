"""Heartbeats: NodeStatus carries a node's traffic, drops and errors; NodeMonitor tracks liveness."""

from __future__ import annotations

import time

import msgpack
import zmq
from bushelpers import sample_messages, wait_until

from stg_node.bus import Bus, BusConfig, NodeMonitor, NodeStatus, Subscriber
from stg_node.bus.codec import encode


def _statuses(sub, node, until, timeout=30.0):
    """NodeStatus messages of ``node`` until ``until(status)`` holds (or timeout)."""
    deadline = time.monotonic() + timeout
    seen = []
    while time.monotonic() < deadline:
        msg = sub.recv(timeout=0.5)
        if isinstance(msg, NodeStatus) and msg.node == node:
            seen.append(msg)
            if until(msg):
                break
    return seen


def test_bus_heartbeat_reports_traffic_drops_and_a_final_stopping(url, broker, ctx):
    config = BusConfig(url=url)
    with Subscriber(config, ["node/status"], context=ctx) as watcher:
        bus = Bus(config, node="tracker", heartbeat_s=0.1)
        try:
            poses = bus.subscribe("body/pose")
            assert bus.publisher.wait_for_subscribers("body/pose")
            for _ in range(5):
                bus.publish(sample_messages()["BodyPose"])
            assert len(list(poses.messages(timeout=30, count=5))) == 5
            # A peer sends a message of a version we do not speak: a counted drop.
            bad = encode(sample_messages()["BodyPose"], topic="body/pose", seq=0, src="old-node", stamp_ns=1)
            header = msgpack.unpackb(bad[1])
            header["v"] = 0
            raw = ctx.socket(zmq.XPUB)  # sees the subscriptions arrive: no guessing
            raw.connect(config.endpoint("reliable", "in"))
            assert raw.poll(30_000) and raw.recv()
            raw.send_multipart([bad[0], msgpack.packb(header), *bad[2:]], copy=False)
            assert wait_until(
                lambda: poses.recv(timeout=0.1) is None and poses.traffic.drops.get("version") == 1, 30
            )
            seen = _statuses(watcher, "tracker", lambda s: s.drops.get("version") == 1)
        finally:
            bus.close()
        final = _statuses(watcher, "tracker", lambda s: s.state == "stopping")
    status = seen[-1]
    assert status.published["body/pose"] == 5 and status.received["body/pose"] == 5
    assert status.drops == {"version": 1}
    assert status.period_s == 0.1 and status.pid > 0 and status.header.src == "tracker"
    assert final and final[-1].state == "stopping"


def test_node_monitor_alive_and_silent():
    now = [100.0]
    monitor = NodeMonitor(missed=3, clock=lambda: now[0])
    monitor.update(NodeStatus(node="a", period_s=1.0))
    monitor.update(NodeStatus(node="b", period_s=0.5))
    assert monitor.alive() == ["a", "b"]
    now[0] += 2.0  # b missed 4 periods, a only 2
    assert monitor.silent() == ["b"] and monitor.alive() == ["a"]
    monitor.update(NodeStatus(node="a", state="stopping"))
    assert monitor.silent() == ["a", "b"]
