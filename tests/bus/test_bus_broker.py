"""The broker: forwarding, the last-value cache for latched topics, status, and its pitfalls."""

from __future__ import annotations

import os
import time

import msgpack
import numpy as np
import pytest
import zmq
from bushelpers import recv_raw, sample_messages, wait_until

from stg_node.bus import BodyPose, Broker, BrokerRunning, BusConfig, GaussianSnapshot, Publisher, Subscriber
from stg_node.bus.codec import encode


def _snapshot(version: int) -> GaussianSnapshot:
    snap = sample_messages()["GaussianSnapshot"]
    snap.model_version = version
    return snap


def test_late_joiner_gets_the_latest_snapshot_at_once_and_only_once(url, broker, ctx):
    config = BusConfig(url=url)
    with (
        Publisher(config, node="trainer", context=ctx) as pub,
        Subscriber(config, [GaussianSnapshot], context=ctx) as early,
    ):
        # The broker subscribes to every latched message itself, so the publisher sees a
        # subscriber at once; snapshot 0 arriving (live or from the cache) shows that early's
        # own subscription is in place before the ones it must see live.
        assert pub.wait_for_subscribers("avatar/snapshot")
        pub.publish(_snapshot(0))
        assert early.recv(timeout=30).model_version == 0
        pub.publish(_snapshot(1))
        pub.publish(_snapshot(2))
        assert [m.model_version for m in early.messages(timeout=30, count=2)] == [1, 2]
        with Subscriber(config, [GaussianSnapshot], context=ctx) as late:
            first = late.recv(timeout=30)  # nothing is published now: only the cache can answer
            assert first.model_version == 2 and first.header.seq == 2
            np.testing.assert_array_equal(first.arrays["xyz"], _snapshot(2).arrays["xyz"])
            assert late.recv(timeout=0.3) is None  # exactly one cached model
            assert early.recv(timeout=0.3) is None  # nobody else saw it again
            pub.publish(_snapshot(3))
            assert late.recv(timeout=30).model_version == 3
            assert early.recv(timeout=30).model_version == 3
    assert early.traffic.duplicates == 0 and late.traffic.drops == {}


def test_a_snapshot_published_while_nobody_listens_is_latched(ipc_url, ctx):
    """Issue 13's gap: publishers filter on their side, so the broker's upstream socket must
    subscribe to latched lanes itself; a renderer started after the trainer's last snapshot
    still gets it. Also after a whole-bus subscriber came and went (its "" unsubscription
    must not cancel the broker's own)."""
    config = BusConfig(url=ipc_url)
    with Broker(ipc_url, status_period_s=0) as broker, Publisher(config, node="trainer", context=ctx) as pub:
        passerby = ctx.socket(zmq.SUB)
        passerby.connect(config.endpoint("bulk", "out"))
        passerby.subscribe(b"")
        assert passerby.poll(30_000) and passerby.recv() == b""  # the broker's no-op: it has it
        events = broker.subscription_events
        passerby.close(linger=0)
        assert wait_until(lambda: broker.subscription_events > events, 30)  # the "" unsubscription
        assert pub.wait_for_subscribers("avatar/snapshot", timeout=30)  # the broker itself
        pub.publish(_snapshot(9))
        assert wait_until(lambda: b"avatar/snapshot" in broker.cache, 30)
        raw = ctx.socket(zmq.SUB)  # raw pyzmq: the late renderer
        raw.connect(config.endpoint("bulk", "out"))
        raw.subscribe(b"avatar/snapshot")
        frames = recv_raw(raw)
        raw.close(linger=0)
        with Subscriber(config, [GaussianSnapshot], context=ctx) as late:
            got = late.recv(timeout=30)
    header = msgpack.unpackb(frames[1].buffer)
    assert (frames[0].bytes, header["model_version"], header["src"]) == (b"avatar/snapshot", 9, "trainer")
    assert got is not None and got.model_version == 9
    np.testing.assert_array_equal(got.arrays["xyz"], _snapshot(9).arrays["xyz"])


def test_the_camera_lane_is_not_pulled_without_subscribers(ipc_url, ctx):
    """Only lanes that carry latched topics subscribe upstream on their own: a camera frame
    with nobody listening stays at its publisher (PUB-side filtering), never crossing to the broker."""
    config = BusConfig(url=ipc_url)
    with Broker(ipc_url, status_period_s=0) as broker, Publisher(config, context=ctx) as pub:
        assert broker.latch_lanes == {"bulk"}
        assert pub.wait_for_subscribers("avatar/snapshot", timeout=5)
        assert not pub.has_subscribers("camera/frame") and not pub.has_subscribers("body/pose")
        pub.publish(sample_messages()["Frame"])
        pub.publish(sample_messages()["BodyPose"])
        time.sleep(0.3)
        assert "camera/frame" not in broker.traffic.messages and "body/pose" not in broker.traffic.messages


def test_a_latched_topic_moved_to_another_lane_is_pulled_there(ipc_url, ctx):
    config = BusConfig(url=ipc_url, lanes={"avatar/snapshot": "reliable"})
    with Broker(ipc_url, status_period_s=0, lanes={"avatar/snapshot": "reliable"}) as broker:
        assert broker.latch_lanes == {"reliable"}
        with Publisher(config, context=ctx) as pub:
            assert pub.wait_for_subscribers("avatar/snapshot", timeout=30)
            pub.publish(_snapshot(3))
            assert wait_until(lambda: b"avatar/snapshot" in broker.cache, 30)
            with Subscriber(config, [GaussianSnapshot], context=ctx) as late:
                assert late.recv(timeout=30).model_version == 3


def test_raw_late_joiner_gets_the_latched_snapshot(ipc_url, ctx):
    config = BusConfig(url=ipc_url)
    with Broker(ipc_url, status_period_s=0), Publisher(config, context=ctx) as pub:
        probe = ctx.socket(zmq.SUB)  # something must subscribe for the broker to forward
        probe.connect(config.endpoint("bulk", "out"))
        probe.subscribe(b"avatar/snapshot")
        assert pub.wait_for_subscribers("avatar/snapshot")
        pub.publish(_snapshot(7))
        recv_raw(probe)
        raw = ctx.socket(zmq.SUB)
        raw.connect(config.endpoint("bulk", "out"))
        raw.subscribe(b"avatar/snapshot")
        frames = recv_raw(raw)
    header = msgpack.unpackb(frames[1].buffer)
    assert frames[0].bytes == b"avatar/snapshot"
    assert (header["type"], header["model_version"], header["num_gaussians"]) == ("GaussianSnapshot", 7, 50)
    names = [d["name"] for d in header["arrays"]]
    xyz = frames[2 + names.index("xyz")]
    np.testing.assert_array_equal(np.frombuffer(xyz.buffer, "<f4").reshape(50, 3), _snapshot(7).arrays["xyz"])


def test_latched_topics_are_cached_per_namespace(ipc_url, ctx):
    with Broker(ipc_url, status_period_s=0) as broker:
        rig1 = BusConfig(url=ipc_url, namespace="rig1")
        with (
            Publisher(rig1, context=ctx) as pub,
            Subscriber(BusConfig(url=ipc_url), ["rig1/", "rig2/"], context=ctx) as watcher,
        ):
            assert pub.wait_for_subscribers("avatar/snapshot")
            assert pub.wait_for_subscribers("/rig2/avatar/snapshot")
            pub.publish(_snapshot(1))
            pub.publish(_snapshot(2), "/rig2/avatar/snapshot")
            assert len(list(watcher.messages(timeout=30, count=2))) == 2
            assert wait_until(
                lambda: set(broker.cache) == {b"rig1/avatar/snapshot", b"rig2/avatar/snapshot"}, 30
            )
            with Subscriber(
                BusConfig(url=ipc_url, namespace="rig2"), [GaussianSnapshot], context=ctx
            ) as late:
                got = list(late.messages(timeout=30, count=1))
                assert late.recv(timeout=0.3) is None  # rig2's model, and only it
    assert [(m.header.topic, m.model_version) for m in got] == [("rig2/avatar/snapshot", 2)]


def test_a_broken_snapshot_is_forwarded_but_never_cached(ipc_url, ctx):
    config = BusConfig(url=ipc_url)
    with (
        Broker(ipc_url, status_period_s=0) as broker,
        Publisher(config, context=ctx) as pub,
        Subscriber(config, [GaussianSnapshot], context=ctx) as early,
    ):
        assert pub.wait_for_subscribers("avatar/snapshot")
        pub.publish(_snapshot(1))
        raw = ctx.socket(zmq.XPUB)  # sees the broker's subscription arrive: no guessing
        raw.connect(config.endpoint("bulk", "in"))
        assert raw.poll(30_000) and raw.recv()
        broken = encode(_snapshot(2), topic="avatar/snapshot", seq=1, src="trainer", stamp_ns=1)
        raw.send_multipart([*broken[:2], b"short"] + broken[3:], copy=False)
        assert early.recv(timeout=30).model_version == 1
        # the broken one reaches the subscriber, which drops it (nothing else is published)
        assert wait_until(lambda: early.recv(timeout=0.1) is None and early.traffic.drops == {"bytes": 1}, 30)
        assert wait_until(lambda: broker.traffic.drops.get("bytes") == 1, 30)
        with Subscriber(config, [GaussianSnapshot], context=ctx) as late:
            assert late.recv(timeout=30).model_version == 1


def test_subscribers_coming_and_going_never_cost_others_a_message(url, broker, ctx):
    """XPUB_MANUAL_LAST_VALUE aims the next send after any (un)subscription at that one
    subscriber; the broker must settle that every time, or live messages go astray."""
    config = BusConfig(url=url)
    with Publisher(config, context=ctx) as pub, Subscriber(config, [BodyPose], context=ctx) as steady:
        assert pub.wait_for_subscribers("body/pose")
        sent = 0
        for _round in range(5):
            events = broker.subscription_events
            with Subscriber(config, ["trainer/metrics", BodyPose], context=ctx) as visitor:
                assert wait_until(lambda e=events: broker.subscription_events >= e + 2, 30)  # both in
                for _ in range(3):
                    pub.publish(sample_messages()["BodyPose"])
                    sent += 1
                assert len(list(visitor.messages(timeout=30, count=1))) == 1
                events = broker.subscription_events
            assert wait_until(lambda e=events: broker.subscription_events >= e + 2, 30)  # both out
            pub.publish(sample_messages()["BodyPose"])
            sent += 1
        got = list(steady.messages(timeout=30, count=20))
        assert steady.recv(timeout=0.3) is None
    assert len(got) == sent == 20
    assert steady.traffic.drops == {}


def test_broker_publishes_its_status(ipc_url, ctx):
    config = BusConfig(url=ipc_url)
    with (
        Broker(ipc_url, status_period_s=0.1),
        Publisher(config, context=ctx) as pub,
        Subscriber(config, ["node/status", BodyPose], context=ctx) as sub,
    ):
        assert pub.wait_for_subscribers("body/pose")
        for _ in range(4):
            pub.publish(sample_messages()["BodyPose"])
        deadline = time.monotonic() + 30
        status = None
        while time.monotonic() < deadline:
            msg = sub.recv(timeout=0.5)
            if getattr(msg, "node", None) == "broker" and msg.received.get("body/pose") == 4:
                status = msg
                break
    assert status is not None
    assert status.state == "running" and status.period_s == pytest.approx(0.1)
    assert status.header.src == "broker"


def test_a_second_broker_on_the_same_ipc_path_is_refused(ipc_url):
    with Broker(ipc_url, status_period_s=0):
        with pytest.raises(BrokerRunning, match="already serves"):
            Broker(ipc_url, status_period_s=0)


def test_one_broker_serves_ipc_and_tcp_together(ipc_url, tcp_url, ctx):
    with Broker([ipc_url, tcp_url], status_period_s=0):
        with (
            Publisher(BusConfig(url=ipc_url), context=ctx) as pub,
            Subscriber(BusConfig(url=tcp_url), [BodyPose], context=ctx) as sub,
        ):
            assert pub.wait_for_subscribers("body/pose")
            pub.publish(sample_messages()["BodyPose"])
            assert isinstance(sub.recv(timeout=30), BodyPose)


def test_broker_removes_its_ipc_files(ipc_dir):
    url = f"ipc://{ipc_dir}/bus"
    with Broker(url, status_period_s=0):
        assert len(os.listdir(ipc_dir)) == 6  # 3 lanes x (in, out)
    assert os.listdir(ipc_dir) == []
