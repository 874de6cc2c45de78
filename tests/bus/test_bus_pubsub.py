"""Publisher and Subscriber against raw pyzmq as the independent truth, on ipc, tcp and inproc."""

from __future__ import annotations

import logging
import time

import msgpack
import numpy as np
import pytest
import zmq
from bushelpers import assert_same_message, keep_last_holds, recv_raw, sample_messages, wait_until

from stg_node.bus import BodyPose, Broker, BusConfig, Frame, Publisher, Subscriber
from stg_node.bus.codec import encode

# --- ours <-> raw pyzmq ---------------------------------------------------------------------------


def _raw_decode(frames):
    """Decode per proto/ with nothing but msgpack and numpy."""
    header = msgpack.unpackb(frames[1].buffer)
    arrays = {
        d["name"]: np.frombuffer(f.buffer, dtype=np.dtype(d["dtype"]).newbyteorder("<")).reshape(d["shape"])
        for d, f in zip(header["arrays"], frames[2:], strict=True)
    }
    return frames[0].bytes.decode(), header, arrays


def test_raw_sub_decodes_our_publisher(url, ctx):
    config = BusConfig(url=url)
    msg = sample_messages()["BodyPose"]
    with Publisher(config, node="tracker", context=ctx, bind=True) as pub:
        raw = ctx.socket(zmq.SUB)
        raw.connect(config.endpoint("reliable", "out"))
        raw.subscribe(b"body/pose")
        assert pub.wait_for_subscribers("body/pose", timeout=5)
        seq = pub.publish(msg, stamp_ns=123)
        topic, header, arrays = _raw_decode(recv_raw(raw))
    assert topic == "body/pose" and seq == 0
    assert (header["type"], header["v"], header["seq"], header["stamp_ns"], header["src"]) == (
        "BodyPose",
        1,
        0,
        123,
        "tracker",
    )
    assert header["frame_seq"] == 3 and header["confidence"] == pytest.approx(0.9)
    for name in ("poses", "Rh", "Th", "betas"):
        np.testing.assert_array_equal(arrays[name], getattr(msg, name))
        assert arrays[name].dtype == np.float32


def test_our_subscriber_reads_raw_pyzmq_messages(url, ctx):
    config = BusConfig(url=url)
    xpub = ctx.socket(zmq.XPUB)  # raw, and it tells us when the subscription has arrived
    xpub.bind(config.endpoint("reliable", "out"))
    with Subscriber(config, ["body/pose"], context=ctx) as sub:
        assert xpub.poll(5000) and xpub.recv() == b"\x01body/pose"
        poses = np.arange(72, dtype=np.float32).reshape(24, 3)
        header = {
            "type": "BodyPose",
            "v": 1,
            "seq": 0,
            "stamp_ns": 5,
            "src": "raw",
            "frame_seq": 9,
            "arrays": [
                {"name": "poses", "dtype": "float32", "shape": [24, 3]},
                {"name": "Rh", "dtype": "float32", "shape": [3]},
                {"name": "Th", "dtype": "float32", "shape": [3]},
                {"name": "betas", "dtype": "float32", "shape": [10]},
            ],
        }
        z3, z10 = np.zeros(3, np.float32), np.ones(10, np.float32)
        xpub.send_multipart([b"body/pose", msgpack.packb(header), poses, z3, z3, z10])
        got = sub.recv(timeout=5)
    assert isinstance(got, BodyPose)
    np.testing.assert_array_equal(got.poses, poses)
    np.testing.assert_array_equal(got.betas, z10)
    assert (got.frame_seq, got.confidence, got.header.src, got.header.stamp_ns) == (9, 1.0, "raw", 5)


def test_through_the_broker_both_ways(url, broker, ctx):
    config = BusConfig(url=url)
    messages = sample_messages()
    raw = ctx.socket(zmq.SUB)
    raw.connect(config.endpoint("latest", "out"))
    raw.subscribe(b"avatar/image")
    with (
        Publisher(config, node="renderer", context=ctx) as pub,
        Subscriber(config, ["avatar/image", "trainer/metrics"], context=ctx) as sub,
    ):
        assert pub.wait_for_subscribers("avatar/image") and pub.wait_for_subscribers("trainer/metrics")
        pub.publish(messages["RenderedImage"])
        pub.publish(messages["TrainerMetrics"])
        got = {type(m).__name__: m for m in sub.messages(timeout=2.0, count=2)}
        topic, header, arrays = _raw_decode(recv_raw(raw))
    assert_same_message(messages["RenderedImage"], got["RenderedImage"])
    assert_same_message(messages["TrainerMetrics"], got["TrainerMetrics"])
    assert topic == "avatar/image" and header["type"] == "RenderedImage"
    np.testing.assert_array_equal(arrays["image"], messages["RenderedImage"].image)


def test_zero_copy_end_to_end_over_inproc(ctx):
    """Over inproc the received array must be the sent memory itself: no copy anywhere."""
    config = BusConfig(url="inproc://zero-copy")
    image = np.random.default_rng(0).integers(0, 256, (512, 683, 3), dtype=np.uint8)  # 1 MB
    frame = Frame(index=0, image=image, K=np.eye(3), R=np.eye(3), t=np.zeros(3))
    with (
        Publisher(config, context=ctx, bind=True) as pub,
        Subscriber(config, ["bench/frames"], context=ctx) as sub,
    ):
        assert pub.wait_for_subscribers("bench/frames")
        pub.publish(frame, "bench/frames")
        got = sub.recv(timeout=5)
        assert got.image.ctypes.data == image.ctypes.data
        assert not got.image.flags.writeable  # a view of the message, read-only


# --- ordering, losses, duplicates --------------------------------------------------------------------


def test_reliable_lane_delivers_every_message_in_order(url, broker, ctx):
    config = BusConfig(url=url)
    msg = sample_messages()["BodyPose"]
    with (
        Publisher(config, node="tracker", context=ctx) as pub,
        Subscriber(config, [BodyPose], context=ctx) as sub,
    ):
        assert pub.wait_for_subscribers("body/pose")
        for i in range(1500):
            msg.frame_index = i
            pub.publish(msg)
        got = list(sub.messages(timeout=30.0, count=1500))
    assert [m.frame_index for m in got] == list(range(1500))
    assert [m.header.seq for m in got] == list(range(1500))
    assert sub.traffic.drops == {} and sub.traffic.messages == {"body/pose": 1500}


def _raw_pose(seq: int, src: str = "raw") -> list:
    msg = sample_messages()["BodyPose"]
    return encode(msg, topic="body/pose", seq=seq, src=src, stamp_ns=1)


def test_gaps_duplicates_and_restarts_are_counted(ipc_url, ctx):
    config = BusConfig(url=ipc_url)
    xpub = ctx.socket(zmq.XPUB)
    xpub.bind(config.endpoint("reliable", "out"))
    with Subscriber(config, ["body/pose"], context=ctx) as sub:
        assert xpub.poll(5000) and xpub.recv()
        for seq in [0, 1, 2, 5, 6, 6, 0, 1]:
            xpub.send_multipart(_raw_pose(seq), copy=False)
        got = [m.header.seq for m in sub.messages(timeout=30.0, count=7)]
    assert got == [0, 1, 2, 5, 6, 0, 1]
    assert sub.traffic.drops == {"lost": 2}
    assert (sub.traffic.duplicates, sub.traffic.restarts) == (1, 1)


def test_sequences_are_per_topic_and_source(ipc_url, ctx):
    config = BusConfig(url=ipc_url)
    xpub = ctx.socket(zmq.XPUB)
    xpub.bind(config.endpoint("reliable", "out"))
    with Subscriber(config, ["body/pose"], context=ctx) as sub:
        assert xpub.poll(5000) and xpub.recv()
        for seq, src in [(0, "a"), (0, "b"), (1, "a"), (1, "b"), (2, "a")]:
            xpub.send_multipart(_raw_pose(seq, src), copy=False)
        got = [(m.header.src, m.header.seq) for m in sub.messages(timeout=30.0, count=5)]
    assert len(got) == 5 and sub.traffic.drops == {}


# --- keep-last --------------------------------------------------------------------------------------


def _frame(index: int) -> Frame:
    return Frame(
        index=index, image=np.full((4, 4, 3), index % 256, np.uint8), K=np.eye(3), R=np.eye(3), t=np.zeros(3)
    )


def test_keep_last_lane_hands_out_only_the_newest_frame(url, ctx):
    config = BusConfig(url=url)
    with (
        Publisher(config, context=ctx, bind=True) as pub,
        Subscriber(config, ["camera/frame"], context=ctx) as sub,
    ):
        assert pub.wait_for_subscribers("camera/frame")
        # A stream the reader thread keeps up with (each frame sent once the one before reached
        # it), while the application is busy and does not read: the newest frame is always there.
        for i in range(20):
            pub.publish(_frame(i))
            assert wait_until(lambda i=i: keep_last_holds(sub, "camera/frame", i), 30)
        assert sub.recv(timeout=2).index == 19
        assert sub.recv(timeout=0.2) is None
        for i in range(20, 40):
            pub.publish(_frame(i))
            assert wait_until(lambda i=i: keep_last_holds(sub, "camera/frame", i), 30)
        newest = sub.recv(timeout=2)
    assert newest.index == 39
    assert sub.traffic.drops == {"superseded": 19}  # seq 20..38 skipped by policy, counted


def test_keep_last_is_per_topic(ipc_url, ctx):
    config = BusConfig(url=ipc_url, namespace="rig1")
    with (
        Publisher(config, context=ctx, bind=True) as pub,
        Subscriber(config, ["camera/frame", "/rig2/camera/frame"], context=ctx) as sub,
    ):
        assert pub.wait_for_subscribers("camera/frame") and pub.wait_for_subscribers("/rig2/camera/frame")
        for i in range(5):
            pub.publish(_frame(i))
            pub.publish(_frame(100 + i), "/rig2/camera/frame")
            assert wait_until(lambda i=i: keep_last_holds(sub, "rig1/camera/frame", i), 30)
            assert wait_until(lambda i=i: keep_last_holds(sub, "rig2/camera/frame", i), 30)
        got = {m.header.topic: m.index for m in sub.messages(timeout=5.0, count=2)}
    assert got == {"rig1/camera/frame": 4, "rig2/camera/frame": 104}


def test_keep_last_can_be_turned_off(ipc_url, ctx):
    config = BusConfig(url=ipc_url, lanes={"camera/frame": "reliable"})  # e.g. replaying a dataset
    with (
        Publisher(config, context=ctx, bind=True) as pub,
        Subscriber(config, ["camera/frame"], context=ctx) as sub,
    ):
        assert pub.wait_for_subscribers("camera/frame")
        for i in range(50):
            pub.publish(_frame(i))
        assert [m.index for m in sub.messages(timeout=30.0, count=50)] == list(range(50))


# --- topics and API -----------------------------------------------------------------------------------


def test_namespaces_absolute_topics_and_type_checks(ipc_url, ctx):
    config = BusConfig(url=ipc_url, namespace="rig1")
    raw = ctx.socket(zmq.SUB)
    raw.connect(config.endpoint("reliable", "out"))
    raw.subscribe(b"")
    with Publisher(config, context=ctx, bind=True) as pub:
        assert pub.wait_for_subscribers()
        pub.publish(sample_messages()["BodyPose"])
        pub.publish(sample_messages()["BodyPose"], "/lab/body/pose")
        topics = {recv_raw(raw)[0].bytes for _ in range(2)}
        with pytest.raises(ValueError, match="carries BodyPose"):
            pub.publish(sample_messages()["NodeStatus"], "body/pose")
        with pytest.raises(ValueError, match="not valid"):
            pub.publish(sample_messages()["BodyPose"], "body pose")
    assert topics == {b"rig1/body/pose", b"lab/body/pose"}


def test_exact_topics_only_although_zeromq_matches_prefixes(ipc_url, ctx):
    config = BusConfig(url=ipc_url)
    with (
        Publisher(config, context=ctx, bind=True) as pub,
        Subscriber(config, ["body/pose"], context=ctx) as sub,
    ):
        assert pub.wait_for_subscribers("body/pose")
        pub.publish(sample_messages()["BodyPose"], "body/pose_debug")  # same prefix, other topic
        pub.publish(sample_messages()["BodyPose"])
        got = list(sub.messages(timeout=30.0, count=1))  # the other topic's would come first
    assert [m.header.topic for m in got] == ["body/pose"]
    assert sub.traffic.drops == {}


def test_recv_timeout_poll_and_iteration(ipc_url, ctx):
    config = BusConfig(url=ipc_url)
    with Publisher(config, context=ctx, bind=True) as pub, Subscriber(config, [BodyPose], context=ctx) as sub:
        start = time.monotonic()
        assert sub.recv(timeout=0.2) is None
        assert time.monotonic() - start >= 0.15  # it waited its timeout out
        assert not sub.poll(timeout=0.05)
        assert pub.wait_for_subscribers("body/pose")
        for _ in range(3):
            pub.publish(sample_messages()["BodyPose"])
        assert sub.poll(timeout=2)
        first = next(iter(sub))  # plain iteration (blocks): safe here, poll() saw a valid message waiting
        seen = [first.header.seq] + [m.header.seq for m in sub.messages(timeout=2.0, count=2)]
    assert seen == [0, 1, 2]


def test_wait_for_subscribers_times_out_without_any(ipc_url, ctx):
    with Publisher(BusConfig(url=ipc_url), context=ctx, bind=True) as pub:
        start = time.monotonic()
        assert not pub.wait_for_subscribers("body/pose", timeout=0.2)
        assert time.monotonic() - start >= 0.15  # it waited its timeout out, then said no
        assert not pub.has_subscribers()


def test_publishing_a_broken_message_raises_and_sends_nothing(ipc_url, ctx):
    config = BusConfig(url=ipc_url)
    with Publisher(config, context=ctx, bind=True) as pub, Subscriber(config, [BodyPose], context=ctx) as sub:
        assert pub.wait_for_subscribers("body/pose")
        bad = sample_messages()["BodyPose"]
        bad.poses = np.zeros((23, 3), np.float32)
        with pytest.raises(ValueError, match="BodyPose.poses"):
            pub.publish(bad)
        assert pub.publish(sample_messages()["BodyPose"]) == 0  # the failed one consumed no seq
        assert sub.recv(timeout=30).header.seq == 0


# --- a flood of bad messages ---------------------------------------------------------------------------


def test_flood_from_one_publisher_is_counted_logged_once_and_loses_nothing_else(ipc_url, ctx, caplog):
    config = BusConfig(url=ipc_url)
    flood = ctx.socket(zmq.XPUB)  # sees the subscription arrive: no guessing how long it takes
    flood.sndhwm = 0  # unlimited: every flood message reaches the subscriber
    flood.connect(config.endpoint("reliable", "in"))
    good_pose = sample_messages()["BodyPose"]
    bad_version = encode(good_pose, topic="body/pose", seq=0, src="flooder", stamp_ns=1)
    header = msgpack.unpackb(bad_version[1])
    header["v"] = 99
    bad_version[1] = msgpack.packb(header)
    garbage = [b"body/pose", b"\xc1 not msgpack"]
    caplog.set_level(logging.WARNING, logger="stg_node.bus")
    with (
        Broker(ipc_url, status_period_s=0),
        Publisher(config, node="tracker", context=ctx) as pub,
        Subscriber(config, [BodyPose], context=ctx) as sub,
    ):
        assert pub.wait_for_subscribers("body/pose", 30)
        assert flood.poll(30_000) and flood.recv() == b"\x01body/pose"  # the flood's subscription
        for i in range(3000):
            flood.send_multipart(bad_version if i % 3 else garbage, copy=False)
            if i % 30 == 0:
                good_pose.frame_index = i // 30
                pub.publish(good_pose)
        got = []

        def everything_read():  # the 100 good ones and the 3000 bad ones, counted as they are read
            if (msg := sub.recv(timeout=0.1)) is not None:
                got.append(msg)
            return len(got) >= 100 and sum(sub.traffic.drops.values()) >= 3000

        assert wait_until(everything_read, 60, step=0), (len(got), sub.traffic.drops)
    assert [m.frame_index for m in got] == list(range(100))
    assert [m.header.src for m in got] == ["tracker"] * 100
    assert sub.traffic.drops == {"version": 2000, "malformed": 1000}
    lines = [r.getMessage() for r in caplog.records if "dropped" in r.getMessage()]
    assert len([line for line in lines if "flooder@body/pose" in line]) == 1
    assert len([line for line in lines if "?@body/pose" in line]) == 1
    assert len(lines) == 2
