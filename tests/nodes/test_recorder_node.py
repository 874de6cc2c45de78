"""The recorder node: a launch with it records what crossed the bus, read back with the mcap package
alone (byte-exact payloads, counts, order, the launch file stored, a finished file)."""

from __future__ import annotations

import io
import json
import sys
import textwrap
from pathlib import Path

import msgpack
from mcap.reader import make_reader
from nodehelpers import ROOT, NodeThread, launch_file
from sample_nodes import pose

from stg_node.bus import BusConfig, encode
from stg_node.bus.recording.format import MESSAGE_ENCODING, META_END, META_LAUNCH
from stg_node.launch import read_launch
from stg_node.launch.process import OutputSink
from stg_node.launch.supervisor import Launcher
from stg_node.nodes.params import ParamError, parse_params
from stg_node.nodes.recorder import RecorderNode, RecorderParams

ECHO = "tests.nodes.sample_nodes:Echo"
COUNT = 20
STAMP0 = 1_700_000_000_000_000_000

# A publisher process: COUNT poses with known stamps, sent once the echo node's own subscription
# (not only the recorder's subscription to everything) has reached it; it ends (and with it the
# launch) once the recorder's heartbeat says it has taken every pose and every reply of the echo.
TALKER = textwrap.dedent(
    f"""
    import time
    from stg_node.bus import Bus, NodeStatus
    from tests.bus.bushelpers import wait_until
    from tests.nodes.sample_nodes import pose
    with Bus(node="talker", heartbeat_s=0) as bus:
        pub = bus.publisher
        assert wait_until(lambda: pub.has_subscribers() and any(
            b"body/pose" in prefixes for prefixes in pub._subscriptions.values()), 60)
        status = bus.subscribe("node/status")
        for i in range({COUNT}):
            bus.publish(pose(i), stamp_ns={STAMP0} + i)

        def recorded():
            msg = status.recv(timeout=0.5)
            return (isinstance(msg, NodeStatus) and msg.node == "recorder"
                    and msg.received.get("body/pose", 0) >= {COUNT}
                    and msg.received.get("trainer/metrics", 0) >= {COUNT})
        assert wait_until(recorded, 120, step=0), "the recorder did not take everything"
    """
)


def mcap_read(path: Path):
    """Every message (topic, channel, message) and metadata record, by the mcap package alone."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        messages = [(c.topic, c, m) for _s, c, m in reader.iter_messages(log_time_order=False)]
        metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        summary = reader.get_summary()
    return messages, metadata, summary


def test_a_launch_with_the_recorder_records_what_crossed_the_bus(tmp_path):
    out = tmp_path / "session.mcap"
    path = launch_file(
        tmp_path,
        f"""
        nodes:
          - {{name: recorder, kind: recorder, params: {{path: {out}}}, sigint_timeout: 20}}
          - {{name: echo, kind: {ECHO}, after: [recorder]}}
          - name: talker
            cmd: [{sys.executable}, -c, {json.dumps(TALKER)}]
            after: [echo]
            required: true
            cwd: {ROOT}
        """,
    )
    log = io.StringIO()
    code = Launcher(read_launch(path), sink=OutputSink(log, color=False)).run()
    assert code == 0, log.getvalue()
    assert "recorded" in log.getvalue() and "no drops" in log.getvalue()

    messages, metadata, summary = mcap_read(out)
    poses = [m for topic, _c, m in messages if topic == "body/pose"]
    metrics = [m for topic, _c, m in messages if topic == "trainer/metrics"]
    assert len(poses) == COUNT and len(metrics) == COUNT
    assert [m.sequence for m in poses] == list(range(COUNT))  # all of them, in order
    for i, m in enumerate(poses):  # byte for byte what the talker sent
        expected = encode(pose(i), topic="body/pose", seq=i, src="talker", stamp_ns=STAMP0 + i)
        assert m.data == b"".join(bytes(memoryview(f).cast("B")) for f in expected[1:])
        assert m.publish_time == STAMP0 + i
    # the echo's replies, in its order, with the frame index it echoed
    assert [msgpack.unpackb(m.data, raw=False)["iteration"] for m in metrics] == list(range(COUNT))
    assert {c.message_encoding for _t, c, _m in messages} == {MESSAGE_ENCODING}
    assert "node/status" in {topic for topic, _c, _m in messages}  # heartbeats, the recorder's own too
    # the launch file that started it, and a clean end without drops
    assert metadata[META_LAUNCH]["text"] == path.read_text()
    assert metadata[META_END]["clean"] == "true" and json.loads(metadata[META_END]["drops"]) == {}
    assert summary is not None and summary.statistics.message_count == len(messages)


def test_record_arg_of_the_shipped_launch_files_starts_the_recorder(tmp_path):
    for name, extra in (("demo.yaml", {}), ("replay_zju.yaml", {"data_root": str(tmp_path)})):
        spec = read_launch(ROOT / "launch" / name, {**extra, "record": str(tmp_path / "s.mcap")})
        recorder = spec.node("recorder")
        assert recorder.params.path == str(tmp_path / "s.mcap")
        assert "recorder" in spec.node("ingest").after  # nothing is published before it records
        quiet = read_launch(ROOT / "launch" / name, extra)
        assert "recorder" in quiet.skipped and all(n.name != "recorder" for n in quiet.nodes)


def test_recorder_params_are_checked_and_an_unwritable_path_fails_the_node(broker, bus_url, tmp_path):
    try:
        parse_params(RecorderParams, {"path": " "}, where="node 'recorder'")
    except ParamError as exc:
        assert "path is empty" in str(exc)
    else:
        raise AssertionError("an empty path was accepted")
    folder = tmp_path / "a-folder"
    folder.mkdir()
    node = RecorderNode("recorder", RecorderParams(path=str(folder)), BusConfig(url=bus_url), heartbeat_s=0)
    with NodeThread(node) as running:
        running.thread.join(60)
    assert running.code == 1
