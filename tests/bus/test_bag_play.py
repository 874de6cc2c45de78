"""Playing recordings back: the exact recorded bytes reach raw pyzmq and our Subscriber, in the
original timing (scaled by the rate), and in lockstep every message is consumed before the next."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import zmq
from baghelpers import ROOT, encoded_stream
from bushelpers import assert_same_message, expect_first_line

from stg_node.bus import Ack, Broker, Bus, Publisher, Subscriber, TrainerMetrics, decode, lane_endpoint
from stg_node.bus.recording import BagReader, BagWriter, Lockstep, PlaybackError, Player
from stg_node.cli import bag as bag_cli


@pytest.fixture
def broker(ipc_url):
    with Broker(ipc_url, status_period_s=0) as running:
        yield running


def _bag(path, stream):
    with BagWriter(path) as bag:
        for log_time, frames in stream:
            bag.write_frames(frames, log_time)
    return BagReader(path)


def _raw_subscribers(ctx, url):
    socks = []
    for lane in ("latest", "reliable", "bulk"):
        sock = ctx.socket(zmq.SUB)
        sock.linger = 0
        sock.connect(lane_endpoint(url, lane, "out"))
        sock.subscribe(b"")
        socks.append(sock)
    return socks


def _drain(socks, until_count, timeout=30.0):
    poller = zmq.Poller()
    for sock in socks:
        poller.register(sock, zmq.POLLIN)
    got = []
    deadline = time.monotonic() + timeout
    while len(got) < until_count and time.monotonic() < deadline:
        for sock, _ in poller.poll(100):
            frames = sock.recv_multipart()
            if len(frames) == 1 and not frames[0]:
                continue  # the broker's no-op
            got.append(frames)
    return got


def test_replay_sends_the_recorded_bytes_to_raw_pyzmq_and_our_subscriber(broker, ipc_url, tmp_path, ctx):
    stream = encoded_stream(4, step_ns=5_000_000)  # every type, 5 ms apart
    reader = _bag(tmp_path / "s.mcap", stream)
    raw = _raw_subscribers(ctx, ipc_url)
    ours = Subscriber(ipc_url, [""], context=ctx, keep_last=False)
    try:
        # the player waits (up to 30 s) until every topic has a subscriber: no guessing how long
        stats = Player(reader, config=ipc_url, context=ctx, wait_for_subscribers_s=30).run()
        received_raw = _drain(raw, len(stream))
        received_ours = list(ours.messages(timeout=30.0, count=len(stream)))
    finally:
        ours.close()
        for sock in raw:
            sock.close()
    assert stats.published == len(stream)
    for topic in {f[0] for _t, f in stream}:
        sent = [f for _t, f in stream if f[0] == topic]
        assert [f for f in received_raw if f[0] == topic] == sent  # byte for byte, in order
        typed = [m for m in received_ours if m.header.topic == topic.decode()]
        assert len(typed) == len(sent)
        for msg, frames in zip(typed, sent, strict=True):
            assert_same_message(msg, decode(frames))
            assert (msg.header.seq, msg.header.src) == (decode(frames).header.seq, "talker")


class StepClock:
    """A monotonic clock that moves only while the player waits on it (time.monotonic/sleep and
    its stop event's wait): the schedule it keeps can be checked exactly, whatever the load."""

    def __init__(self):
        self.now = 1000.0

    def monotonic(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += max(0.0, seconds)


class StepClockEvent(threading.Event):
    def __init__(self, clock: StepClock):
        super().__init__()
        self.clock = clock

    def wait(self, timeout=None) -> bool:
        if not self.is_set():
            self.clock.sleep(timeout or 0.0)
        return self.is_set()


@pytest.mark.parametrize("rate", [1.0, 2.5])
def test_replay_keeps_the_recorded_timing_scaled_by_the_rate(
    broker, ipc_url, tmp_path, ctx, rate, monkeypatch
):
    """Each message goes out when its recorded offset from the first, divided by the rate, has
    passed on the player's clock (a step clock here, so a busy machine cannot change the answer;
    how close the real schedule is, is a benchmark's business), and every one arrives."""
    from stg_node.bus.recording import player as player_module

    stream = [(t, f) for t, f in encoded_stream(8, step_ns=15_000_000) if f[0] == b"body/pose"]
    gaps = [(b[0] - a[0]) / 1e9 for a, b in zip(stream, stream[1:], strict=False)]  # 105 ms each
    reader = _bag(tmp_path / "s.mcap", stream)
    clock = StepClock()
    monkeypatch.setattr(player_module, "time", clock)
    sent = []
    forward = Publisher.forward

    def forward_and_note(self, frames):
        sent.append(clock.now)
        return forward(self, frames)

    monkeypatch.setattr(Publisher, "forward", forward_and_note)
    with Subscriber(ipc_url, ["body/pose"], context=ctx) as sub:
        player = Player(reader, config=ipc_url, rate=rate, drain_s=0, wait_for_subscribers_s=30, context=ctx)
        player._stop = StepClockEvent(clock)
        thread = threading.Thread(target=player.run)
        thread.start()
        got = [m.header.seq for m in sub.messages(timeout=30.0, count=len(stream))]
        thread.join(30)
    assert got == list(range(len(stream)))
    np.testing.assert_allclose(np.diff(sent), np.array(gaps) / rate, atol=1e-9)


class Consumer:
    """A slow node that acknowledges each frame it has finished with (what lockstep waits for)."""

    def __init__(self, url, *, work_s=0.02, ack_with=None, stray_first=False):
        self.url = url
        self.work_s = work_s
        self.ack_with = ack_with
        self.stray_first = stray_first
        self.seqs: list[int] = []
        self.events: list[tuple[str, int, float]] = []
        self.ready = threading.Event()
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        with Bus(self.url, node="consumer", heartbeat_s=0) as bus:
            frames = bus.subscribe("camera/frame")  # keep-last: lockstep must still deliver every frame
            self.ready.set()
            while not self.stop.is_set():
                frame = frames.recv(timeout=0.1)
                if frame is None:
                    continue
                self.events.append(("recv", frame.header.seq, time.monotonic()))
                self.seqs.append(frame.header.seq)
                time.sleep(self.work_s)
                if self.stray_first:
                    bus.publish(Ack(msg_topic="camera/frame", msg_seq=999, msg_src="nobody"))
                if self.ack_with is not None:
                    bus.publish(self.ack_with)
                else:
                    h = frame.header
                    bus.publish(Ack(msg_topic=h.topic, msg_seq=h.seq, msg_src=h.src))
                self.events.append(("ack", frame.header.seq, time.monotonic()))

    def __enter__(self):
        self.thread.start()
        self.ready.wait(5)
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join(5)


def _frames_bag(path, count):
    stream = [(t, f) for t, f in encoded_stream(count, step_ns=1_000) if f[0] == b"camera/frame"]
    return stream, _bag(path, stream)


def test_lockstep_delivers_every_frame_one_at_a_time_even_as_fast_as_possible(broker, ipc_url, tmp_path):
    stream, reader = _frames_bag(tmp_path / "f.mcap", 25)
    with Consumer(ipc_url, stray_first=True) as consumer:
        player = Player(reader, config=ipc_url, rate=0, lockstep=Lockstep(timeout_s=60), drain_s=0)
        stats = player.run()
    assert consumer.seqs == list(range(25))  # none superseded on the keep-last lane
    assert stats.acks == 25 and stats.stray_acks == 25
    # frame i+1 arrived only after frame i was acknowledged
    acked = {seq: t for kind, seq, t in consumer.events if kind == "ack"}
    for kind, seq, t in consumer.events:
        if kind == "recv" and seq > 0:
            assert t > acked[seq - 1]


def test_lockstep_counts_any_message_on_a_chosen_ack_topic(broker, ipc_url, tmp_path):
    _stream, reader = _frames_bag(tmp_path / "f.mcap", 10)
    metrics = TrainerMetrics(iteration=1, loss=0.5)
    with Consumer(ipc_url, ack_with=metrics, work_s=0.005) as consumer:
        lockstep = Lockstep(ack_topic="trainer/metrics", timeout_s=60)
        stats = Player(reader, config=ipc_url, rate=0, lockstep=lockstep, drain_s=0).run()
    assert consumer.seqs == list(range(10)) and stats.acks == 10


def test_lockstep_fails_clearly_without_a_consumer_or_an_acknowledgement(broker, ipc_url, tmp_path, ctx):
    _stream, reader = _frames_bag(tmp_path / "f.mcap", 3)
    with pytest.raises(PlaybackError, match="nobody subscribes to 'camera/frame'"):
        Player(reader, config=ipc_url, lockstep=Lockstep(timeout_s=0.5), context=ctx).run()
    with Subscriber(ipc_url, ["camera/frame"], context=ctx):  # subscribes, never acknowledges
        with pytest.raises(PlaybackError, match="0 of 1 acknowledgement.*camera/frame seq 0"):
            Player(reader, config=ipc_url, lockstep=Lockstep(timeout_s=0.5), context=ctx).run()


def test_topics_start_offset_and_loop(broker, ipc_url, tmp_path, ctx):
    stream = encoded_stream(6, step_ns=2_000_000)  # 2 ms apart
    reader = _bag(tmp_path / "s.mcap", stream)
    with Subscriber(ipc_url, [""], context=ctx, keep_last=False) as sub:
        player = Player(
            reader, config=ipc_url, rate=0, topics=["pose$", "^avatar/view"], wait_for_subscribers_s=30
        )
        stats = player.run()
        got = [m.header.topic for m in sub.messages(timeout=30.0, count=12)]
        assert sub.recv(timeout=0.3) is None  # and nothing of the other topics
    assert stats.published == 12 and sorted(set(got)) == ["avatar/view", "body/pose"] and len(got) == 12

    offset_s = (stream[21][0] - stream[0][0]) / 1e9
    stats = Player(reader, config=ipc_url, rate=0, start_offset_s=offset_s, drain_s=0, context=ctx).run()
    assert stats.published == len(stream) - 21

    player = Player(
        reader,
        config=ipc_url,
        rate=0,
        loop=True,
        topics=["body/pose"],
        drain_s=0,
        wait_for_subscribers_s=0,
        context=ctx,
    )
    threading.Timer(0.5, player.stop).start()
    stats = player.run()
    assert stats.loops >= 2 and stats.published >= 12


def test_paused_player_sends_nothing_until_stepped_or_resumed(broker, ipc_url, tmp_path, ctx):
    stream = [(t, f) for t, f in encoded_stream(5, step_ns=1_000_000) if f[0] == b"body/pose"]
    reader = _bag(tmp_path / "s.mcap", stream)
    player = Player(reader, config=ipc_url, paused=True, drain_s=0, context=ctx, wait_for_subscribers_s=30)
    with Subscriber(ipc_url, ["body/pose"], context=ctx) as sub:
        thread = threading.Thread(target=player.run)
        thread.start()
        assert sub.recv(timeout=0.4) is None
        player.step()
        assert sub.recv(timeout=30.0).header.seq == 0
        assert sub.recv(timeout=0.3) is None
        player.resume()
        assert [m.header.seq for m in sub.messages(timeout=30.0, count=4)] == [1, 2, 3, 4]
        thread.join(30)


def test_play_cli_paused_resumes_on_sigusr1(broker, ipc_url, tmp_path, ctx):
    stream = [(t, f) for t, f in encoded_stream(3, step_ns=1_000_000) if f[0] == b"body/pose"]
    _bag(tmp_path / "s.mcap", stream)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "STG_LOG_LEVEL": "WARNING"}
    with Subscriber(ipc_url, ["body/pose"], context=ctx) as sub:
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "stg_node.cli.bag",
                "play",
                str(tmp_path / "s.mcap"),
                "--bus",
                ipc_url,
                "--paused",
                "--wait",
                "30",
            ],
            cwd=ROOT,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        expect_first_line(proc, "paused")
        assert sub.recv(timeout=0.5) is None
        proc.send_signal(signal.SIGUSR1)
        assert [m.header.seq for m in sub.messages(timeout=30.0, count=3)] == [0, 1, 2]
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert "published 3 messages" in out


def test_play_cli_bad_usage_and_bad_files(tmp_path, capsys):
    assert bag_cli.main(["play", str(tmp_path / "missing.mcap"), "--rate", "-1"]) == 2
    assert "--rate must be >= 0" in capsys.readouterr().err
    assert bag_cli.main(["play", str(tmp_path / "missing.mcap")]) == 1
    assert "no recording at" in capsys.readouterr().err
    assert bag_cli.main(["play", "x.mcap", "--lockstep", "--acks", "0"]) == 2


def test_forward_refuses_a_broken_or_misplaced_message(ipc_url, ctx):
    good = encoded_stream(1)[1][1]  # body/pose
    with Publisher(ipc_url, context=ctx, bind=True) as pub:
        with pytest.raises(ValueError, match="bytes"):
            pub.forward([good[0], good[1], *good[2:-1]])  # a buffer missing
        with pytest.raises(ValueError, match="type_mismatch"):
            pub.forward([b"camera/frame", *good[1:]])
        assert pub.forward(good).topic == "body/pose"


def test_invalid_recorded_messages_are_skipped_and_counted(broker, ipc_url, tmp_path, ctx):
    import msgpack
    from mcap.writer import Writer

    good = encoded_stream(1)[1][1]  # a body/pose
    path = tmp_path / "mixed.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        channel = w.register_channel("body/pose", "stg-bus", 0)
        w.add_message(channel, 1, b"".join(good[1:]), 1, 0)
        w.add_message(channel, 2, msgpack.packb({"type": "BodyPose", "arrays": []}), 2, 1)  # no seq, src...
        w.add_message(channel, 3, b"\xc1", 3, 2)  # not msgpack at all
        w.add_message(channel, 4, b"".join(good[1:]), 4, 0)
        w.finish()
    with Subscriber(ipc_url, ["body/pose"], context=ctx, keep_last=False) as sub:
        stats = Player(BagReader(path), config=ipc_url, rate=0, context=ctx, wait_for_subscribers_s=30).run()
        got = list(sub.messages(timeout=30.0, count=1))
        assert sub.recv(timeout=0.5) is None  # the second, a duplicate, is skipped on arrival
    assert (stats.published, stats.skipped) == (2, 2)
    assert len(got) == 1 and sub.traffic.duplicates == 1  # the same message twice: a duplicate to receivers
