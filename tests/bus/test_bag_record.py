"""Recording a live bus: what raw pyzmq and our Publisher sent is in the file byte for byte (read by
the mcap package), drops are counted, and a recorder killed with SIGKILL leaves a readable file."""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import time

import msgpack
import numpy as np
import pytest
import zmq
from baghelpers import ROOT, encoded_stream, mcap_messages, wait_written
from bushelpers import expect_first_line, sample_messages, wait_until
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader

from stg_node.bus import Broker, BusConfig, Publisher, Subscriber, lane_endpoint
from stg_node.bus.recording import BagReader, Recorder, bag_info
from stg_node.cli import bag as bag_cli


def _raw_publisher(ctx, url, lane):
    """A raw pyzmq publisher on ``lane``, returned once a subscription has reached it (an XPUB
    sees it arrive; a PUB would drop what it sends before that)."""
    sock = ctx.socket(zmq.XPUB)
    sock.linger = 0
    sock.connect(lane_endpoint(url, lane, "in"))
    assert sock.poll(30_000), f"no subscription reached a raw publisher on {lane}"
    sock.recv()
    return sock


def test_recorder_keeps_exactly_what_raw_pyzmq_and_our_publisher_sent(ipc_url, tmp_path, ctx):
    path = tmp_path / "live.mcap"
    with Broker(ipc_url, status_period_s=0):
        recorder = Recorder(path, config=ipc_url).start()
        try:
            with Publisher(ipc_url, node="ours", context=ctx) as pub:
                assert pub.wait_for_subscribers("body/pose") and pub.wait_for_subscribers("camera/frame")
                raw_reliable = _raw_publisher(ctx, ipc_url, "reliable")
                raw_latest = _raw_publisher(ctx, ipc_url, "latest")
                sent = []
                # a raw header packed differently from ours (floats as float32, keys in another order)
                for seq in range(20):
                    header = {
                        "arrays": [
                            {"name": "K", "dtype": "float64", "shape": [3, 3]},
                            {"name": "R", "dtype": "float64", "shape": [3, 3]},
                            {"name": "t", "dtype": "float64", "shape": [3]},
                        ],
                        "type": "ViewRequest",
                        "v": 1,
                        "seq": seq,
                        "stamp_ns": time.time_ns(),
                        "src": "robot",
                        "width": 640,
                        "height": 480,
                        "near": 0.5,
                        "far": 10.0,
                    }
                    packed = msgpack.packb(header, use_single_float=True)
                    frames = [
                        b"avatar/view",
                        packed,
                        np.eye(3).tobytes(),
                        np.eye(3).tobytes(),
                        np.ones(3).tobytes(),
                    ]
                    raw_reliable.send_multipart(frames)
                    sent.append(frames)
                    image = np.full((6, 8, 3), seq, np.uint8)
                    frame_header = {
                        "type": "Frame",
                        "v": 1,
                        "seq": seq,
                        "stamp_ns": time.time_ns(),
                        "src": "cam",
                        "index": seq,
                        "arrays": [
                            {"name": "image", "dtype": "uint8", "shape": [6, 8, 3]},
                            {"name": "K", "dtype": "float64", "shape": [3, 3]},
                            {"name": "R", "dtype": "float64", "shape": [3, 3]},
                            {"name": "t", "dtype": "float64", "shape": [3]},
                        ],
                    }
                    frames = [
                        b"camera/frame",
                        msgpack.packb(frame_header),
                        image.tobytes(),
                        np.eye(3).tobytes(),
                        np.eye(3).tobytes(),
                        np.zeros(3).tobytes(),
                    ]
                    raw_latest.send_multipart(frames)
                    sent.append(frames)
                    msg = sample_messages(seq)["BodyPose"]
                    pub.publish(msg)
                    # a stream the recorder keeps up with: the keep-last lane (4 deep) drops nothing
                    assert wait_until(lambda n=3 * (seq + 1): recorder.stats().received >= n, 30)
                raw_reliable.close()
                raw_latest.close()
            wait_written(recorder, 60)
        finally:
            stats = recorder.stop()
    assert stats.drops == {} and stats.written == 60

    got = mcap_messages(path)
    by_topic: dict[str, list] = {}
    for topic, _channel, message in got:
        by_topic.setdefault(topic, []).append(message)
    assert sorted(by_topic) == ["avatar/view", "body/pose", "camera/frame"]
    # byte-exact, in order, per topic, for the raw senders
    for topic in ("avatar/view", "camera/frame"):
        expected = [b"".join(f[1:]) for f in sent if f[0].decode() == topic]
        assert [m.data for m in by_topic[topic]] == expected
        assert [m.sequence for m in by_topic[topic]] == list(range(20))
    # our publisher: header seq/src/stamp as sent, arrays as given
    poses = by_topic["body/pose"]
    assert [m.sequence for m in poses] == list(range(20))
    for seq, message in enumerate(poses):
        unpacker = msgpack.Unpacker()
        unpacker.feed(message.data)
        header = unpacker.unpack()
        assert header["src"] == "ours" and header["seq"] == seq and message.publish_time == header["stamp_ns"]
        want = sample_messages(seq)["BodyPose"]
        tail = message.data[unpacker.tell() :]
        assert tail == b"".join(
            np.ascontiguousarray(a).tobytes() for a in (want.poses, want.Rh, want.Th, want.betas)
        )
    # receive times: the order they arrived in, never before they were stamped
    times = [m.log_time for _t, _c, m in got]
    assert times == sorted(times)
    assert all(m.log_time >= m.publish_time for _t, _c, m in got)


def test_topic_regexes_limit_what_is_recorded(ipc_url, tmp_path, ctx):
    path = tmp_path / "poses.mcap"
    with Broker(ipc_url, status_period_s=0):
        with Recorder(path, config=ipc_url, topics=["^body/"]) as recorder:
            with Publisher(ipc_url, node="ours", context=ctx) as pub:
                pub.wait_for_subscribers("body/pose")
                for msg in sample_messages().values():
                    pub.publish(msg)
                # everything reached the recorder (counted, recorded or filtered out)
                assert wait_until(lambda: recorder.stats().filtered == len(sample_messages()) - 1, 30)
                wait_written(recorder, 1)
            stats = recorder.stats()
    assert [t for t, _c, _m in mcap_messages(path)] == ["body/pose"]
    assert stats.filtered == len(sample_messages()) - 1


def test_sequence_gaps_are_reported_as_drops_in_stats_file_and_info(ipc_url, tmp_path, ctx):
    path = tmp_path / "gaps.mcap"
    stream = [f for _t, f in encoded_stream(8) if f[0] == b"body/pose"]
    with Broker(ipc_url, status_period_s=0):
        recorder = Recorder(path, config=ipc_url).start()
        raw = _raw_publisher(ctx, ipc_url, "reliable")
        for index in (0, 1, 5, 6, 7):  # seqs 2, 3 and 4 never sent: 3 lost
            raw.send_multipart(stream[index])
        wait_written(recorder, 5)
        raw.close()
        stats = recorder.stop()
    assert stats.drops == {"lost": 3}
    info = bag_info(BagReader(path))
    assert info.drops == {"lost": 3}
    out = io.StringIO()
    assert bag_cli.main(["info", str(path)], out=out) == 0
    assert "Drops:        3 (3 lost)" in out.getvalue()


def test_a_full_queue_drops_and_counts_instead_of_growing(ipc_url, tmp_path, ctx):
    path = tmp_path / "overflow.mcap"
    with Broker(ipc_url, status_period_s=0):
        recorder = Recorder(path, config=ipc_url, max_queue_bytes=2000).start()
        with Publisher(ipc_url, node="ours", context=ctx) as pub:
            pub.wait_for_subscribers("body/pose")
            pose = sample_messages()["BodyPose"]
            for _ in range(30):  # ~600 B each; nobody calls poll(): the queue fills
                pub.publish(pose)
            assert wait_until(lambda: recorder.stats().received == 30, 30)
        stats = recorder.stop()
    assert stats.drops.get("recorder_overflow", 0) > 0
    assert stats.written + stats.drops["recorder_overflow"] == 30
    assert len(mcap_messages(path)) == stats.written


# --- the recorder as a process: signals and SIGKILL -----------------------------------------------


def _start_recorder(url, path, *extra, ignore_sigint=False):
    env = {**os.environ, "PYTHONPATH": str(ROOT), "STG_LOG_LEVEL": "WARNING"}
    preexec = (lambda: signal.signal(signal.SIGINT, signal.SIG_IGN)) if ignore_sigint else None
    proc = subprocess.Popen(
        [sys.executable, "-m", "stg_node.cli.bag", "record", "-o", str(path), "--bus", url, *extra],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=preexec,
    )
    expect_first_line(proc, "recording")  # "recording ... (Ctrl-C to stop)": subscribed
    return proc


def test_a_child_that_hangs_silently_fails_at_the_deadline_with_its_output():
    """What _start_recorder relies on: no first line by the deadline is a failure naming what the
    child wrote to stderr, and the child is killed rather than left running."""
    hang = "import sys, time; print('stuck', file=sys.stderr, flush=True); time.sleep(120)"
    proc = subprocess.Popen(
        [sys.executable, "-c", hang], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    with pytest.raises(AssertionError, match=r"printed no full line in 1 s.*stderr 'stuck\\n'"):
        expect_first_line(proc, "recording", timeout=1.0)
    assert proc.returncode == -signal.SIGKILL


def _publish_poses(url, ctx, count, first_seq=0, pause=0.0):
    """``count`` poses, sent once the recorder subscribes; returns once an observer beside the
    recorder got all of them: they have left the publisher (closed with LINGER 0, it would drop
    what is still queued) and crossed the broker to every subscriber."""
    with (
        Subscriber(url, ["body/pose"], context=ctx) as observer,
        Publisher(url, node="talker", context=ctx) as pub,
    ):
        assert pub.wait_for_subscribers("body/pose", 30)
        assert wait_until(lambda: _subscribed_twice(pub), 30)  # the recorder's and the observer's
        pose = sample_messages()["BodyPose"]
        for _ in range(count):
            pub.publish(pose)
            if pause:
                time.sleep(pause)
        assert len(list(observer.messages(timeout=30, count=count))) == count


def _subscribed_twice(pub) -> bool:
    """The talker sees a body/pose subscription besides the recorder's whole-bus one."""
    pub.has_subscribers()
    return any(b"body/pose" in seen and b"" in seen for seen in pub._subscriptions.values())


def _messages_on_disk(path) -> int:
    """Messages the mcap package can read from ``path`` as it is now (a file still being written)."""
    count = 0
    try:
        for record in StreamReader(str(path)).records:
            count += type(record).__name__ == "Message"
    except Exception:  # the end of what is written so far
        pass
    return count


@pytest.mark.parametrize("sig, ignore_sigint", [(signal.SIGTERM, False), (signal.SIGINT, True)])
def test_sigterm_or_sigint_finishes_the_file(ipc_url, tmp_path, ctx, sig, ignore_sigint):
    """SIGINT works even when the recorder inherited it ignored (started in the background)."""
    path = tmp_path / "clean.mcap"
    with Broker(ipc_url, status_period_s=0):
        proc = _start_recorder(ipc_url, path, "--flush-interval", "0.2", ignore_sigint=ignore_sigint)
        _publish_poses(ipc_url, ctx, 25)
        assert wait_until(lambda: _messages_on_disk(path) >= 25, 60)  # recorded: now stop it
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert "recorded 25 messages" in out and "no drops" in out
    with open(path, "rb") as f:
        reader = make_reader(f)
        assert reader.get_summary().statistics.message_count == 25
        assert "stg.recording.end" in {m.name for m in reader.iter_metadata()}


def test_kill_9_leaves_a_file_that_reads_back_to_its_last_complete_chunk(ipc_url, tmp_path, ctx):
    path = tmp_path / "killed.mcap"
    with Broker(ipc_url, status_period_s=0):
        proc = _start_recorder(ipc_url, path, "--flush-interval", "0.2")
        _publish_poses(ipc_url, ctx, 40, pause=0.005)
        assert wait_until(lambda: _messages_on_disk(path) >= 40, 60)  # flushed: these 40 are on disk
        with Publisher(ipc_url, node="late", context=ctx) as pub:  # more, killed mid-stream
            pub.wait_for_subscribers("body/pose")
            for _ in range(200):
                pub.publish(sample_messages()["BodyPose"])
            proc.send_signal(signal.SIGKILL)
        proc.communicate(timeout=60)
    assert proc.returncode == -signal.SIGKILL

    # the mcap package alone: read records until the file ends
    recovered = []
    try:
        for record in StreamReader(str(path)).records:
            if type(record).__name__ == "Message":
                recovered.append(record)
    except Exception:  # the truncated end: the stream reader stops there
        pass
    assert len(recovered) >= 40
    first = recovered[:40]
    assert [m.sequence for m in first] == list(range(40))

    reader = BagReader(path)
    bag = reader.files[0]
    assert bag.truncated and bag.problem
    ours = list(reader.messages())
    assert [m.data for m in ours][: len(recovered)] == [m.data for m in recovered][: len(ours)]
    assert len(ours) >= 40

    out = io.StringIO()
    assert bag_cli.main(["info", str(path)], out=out) == 0
    text = out.getvalue()
    assert "TRUNCATED" in text and f"{len(ours)} messages recovered" in text
    out = io.StringIO()
    assert bag_cli.main(["info", "--json", str(path)], out=out) == 0
    assert json.loads(out.getvalue())["truncated"] is True


def test_a_file_cut_inside_a_chunk_recovers_the_chunks_before_it(tmp_path):
    from stg_node.bus.recording import BagWriter

    stream = encoded_stream(10)
    path = tmp_path / "whole.mcap"
    with BagWriter(path, chunk_size=1500) as bag:
        for log_time, frames in stream:
            bag.write_frames(frames, log_time)
    with open(path, "rb") as f:
        chunks = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    cut = chunks[3].chunk_start_offset + chunks[3].chunk_length // 2  # inside the 4th chunk
    damaged = tmp_path / "cut.mcap"
    damaged.write_bytes(path.read_bytes()[:cut])
    reader = BagReader(damaged)
    assert reader.files[0].truncated and "incomplete chunk record" in reader.files[0].problem
    expected = [b"".join(f[1:]) for _t, f in stream]
    got = [m.data for m in reader.messages()]
    assert 0 < len(got) < len(expected) and got == expected[: len(got)]
    assert reader.message_count == len(got)


def test_record_cli_rejects_bad_usage(tmp_path, capsys):
    assert bag_cli.main(["record", "-o", str(tmp_path / "x.mcap"), "--split-size", "0"]) == 2
    assert "--split-size must be > 0" in capsys.readouterr().err
    assert bag_cli.main(["record", "-o", str(tmp_path / "x.mcap"), "--topics", "("]) == 2
    assert "bad topic pattern" in capsys.readouterr().err
    assert bag_cli.main(["record", "-o", str(tmp_path / "x.mcap"), "--bus", "udp://x"]) == 2
    assert bag_cli.main(["record", "-o", str(tmp_path / "x.mcap"), "--compression", "gzip"]) == 2


def test_info_on_a_bad_file_fails_with_exit_1(tmp_path, capsys):
    path = tmp_path / "bad.mcap"
    path.write_text("not a recording")
    assert bag_cli.main(["info", str(path)]) == 1
    assert "is not an MCAP file" in capsys.readouterr().err


def test_recorder_reports_an_unreachable_output(ipc_url, tmp_path):
    from stg_node.bus.recording import RecordingError

    blocker = tmp_path / "file"
    blocker.write_text("x")
    with Broker(ipc_url, status_period_s=0):
        recorder = Recorder(blocker / "sub" / "x.mcap", config=BusConfig(url=ipc_url))
        with pytest.raises(RecordingError, match="cannot write .*x.mcap"):
            recorder.start()


def test_a_bus_it_cannot_join_fails_start_and_leaves_no_file(tmp_path, tcp_url):
    from stg_node.bus.recording import RecordingError

    config = BusConfig(url=tcp_url, keys=tmp_path / "no-keys", key_name="robot")
    recorder = Recorder(tmp_path / "x.mcap", config=config)
    with pytest.raises(RecordingError, match="cannot subscribe"):
        recorder.start()
    assert not (tmp_path / "x.mcap").exists()
