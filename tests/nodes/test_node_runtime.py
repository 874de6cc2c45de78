"""The node runtime: heartbeats, remaps, events, failure and teardown, signals in a real process."""

from __future__ import annotations

import json
import os
import signal
import socket
import time

import pytest
from nodehelpers import LineReader, NodeThread, child_env, ignore_sigint, recv_until, spawn
from sample_nodes import Echo, EchoParams, pose

from stg_node.bus import Bus, BusConfig, Subscriber
from stg_node.bus.messages import NodeStatus, TrainerMetrics
from stg_node.nodes.runtime import Node


def test_a_node_reports_its_identity_rates_and_drops_in_its_heartbeat(broker, bus_url, tmp_path):
    flush = tmp_path / "flushed"
    node = Echo("echo1", EchoParams(flush_file=str(flush)), BusConfig(url=bus_url), heartbeat_s=0.1)
    with (
        Subscriber(BusConfig(url=bus_url), ["node/status", "trainer/metrics"]) as sub,
        NodeThread(node) as run,
    ):
        with Bus(bus_url, node="feeder", heartbeat_s=0) as feeder:
            assert feeder.publisher.wait_for_subscribers("body/pose", 10)
            for i in range(20):
                feeder.publish(pose(i))
                time.sleep(0.01)
            node.drop("on_purpose", 3)
            statuses, metrics = [], []
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:  # until a heartbeat that has seen everything
                msg = sub.recv(timeout=0.5)
                if isinstance(msg, TrainerMetrics):
                    metrics.append(msg.iteration)
                elif isinstance(msg, NodeStatus) and msg.node == "echo1":
                    statuses.append(msg)
                    if (
                        msg.received.get("body/pose") == 20
                        and msg.published.get("trainer/metrics") == 20
                        and msg.drops.get("on_purpose") == 3
                    ):
                        break
        assert run.stop() == 0
    status = statuses[-1]
    assert (status.pid, status.host, status.state) == (os.getpid(), socket.gethostname(), "running")
    assert status.published["trainer/metrics"] == 20 and status.received["body/pose"] == 20
    assert "body/pose" in status.rates_hz and status.drops["on_purpose"] == 3
    assert metrics == list(range(20))
    assert flush.read_text() == "flushed"


def test_remaps_rename_topics_and_events_keep_the_name_the_node_asked_for(broker, bus_url):
    seen = []

    class Probe(Node):
        def setup(self):
            self.subscribe("body/pose")

        def on_message(self, topic, msg):
            seen.append((topic, msg.header.topic))
            self.publish(TrainerMetrics(iteration=1, loss=0.0))

    node = Probe(
        "probe", None, BusConfig(url=bus_url), remap={"body/pose": "rig/body/pose", "trainer/metrics": "m"}
    )
    with Subscriber(BusConfig(url=bus_url), ["m"]) as out, NodeThread(node):
        with Bus(bus_url, node="feeder", heartbeat_s=0) as feeder:
            assert feeder.publisher.wait_for_subscribers("rig/body/pose", 10)
            feeder.publish(pose(1), "body/pose")  # not remapped: the node must not see it
            feeder.publish(pose(2), "rig/body/pose")
            got = out.recv(timeout=30)
    assert seen == [("body/pose", "rig/body/pose")]
    assert got is not None and got.header.topic == "m"


def test_a_failing_node_exits_1_and_still_flushes(broker, bus_url, tmp_path):
    flushed = []

    class Broken(Node):
        tick_s = 0.01

        def on_tick(self):
            raise RuntimeError("boom")

        def teardown(self):
            flushed.append(True)

    with Subscriber(BusConfig(url=bus_url), ["node/status"]) as sub:
        node = Broken("broken", None, BusConfig(url=bus_url), heartbeat_s=0.05)
        assert node.execute() == 1
        last = recv_until(sub, lambda m: m.node == "broken" and m.state == "stopping", 30)
    assert flushed == [True]
    assert last is not None and last.errors >= 1 and "boom" in last.last_error


def _node_process(tmp_path, bus_url, **params):
    params = {"flush_file": str(tmp_path / "flushed"), **params}
    return spawn(
        [
            "-m",
            "stg_node.nodes",
            "tests.nodes.sample_nodes:Echo",
            "--name",
            "bg",
            "--bus",
            bus_url,
            "--params",
            json.dumps(params),
        ],
        preexec_fn=ignore_sigint,
    )


def _wait_for_line(proc, out: LineReader, text: str, timeout: float = 60.0) -> None:
    if not out.wait_for(lambda seen: text in seen, timeout=timeout):
        proc.kill()
        raise AssertionError(f"never printed {text!r}: {out.text()}")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_node_started_with_sigint_ignored_still_stops_cleanly_on_a_signal(broker, bus_url, tmp_path, sig):
    proc = _node_process(tmp_path, bus_url, teardown_s=0.2)
    reader = LineReader(proc.stdout)
    _wait_for_line(proc, reader, "running (pid")
    proc.send_signal(sig)
    out = reader.rest(proc, timeout=20)
    assert proc.returncode == 0, out
    assert f"stopped ({signal.Signals(sig).name})" in out and "Traceback" not in out
    assert (tmp_path / "flushed").read_text() == "flushed"  # teardown ran before the exit


def test_a_second_signal_aborts_a_slow_teardown(broker, bus_url, tmp_path):
    proc = _node_process(tmp_path, bus_url, teardown_s=30)
    reader = LineReader(proc.stdout)
    _wait_for_line(proc, reader, "running (pid")
    proc.send_signal(signal.SIGINT)
    _wait_for_line(proc, reader, "teardown started")  # the second signal must find it in its teardown
    proc.send_signal(signal.SIGINT)
    out = reader.rest(proc, timeout=20)
    assert "teardown interrupted" in out
    assert not (tmp_path / "flushed").exists()


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["tests.nodes.sample_nodes:Echo", "--param", "setup_s=-1"], "param 'setup_s': must be >= 0.0"),
        (["tests.nodes.sample_nodes:Echo", "--param", "colour=red"], "param 'colour': unknown parameter"),
        (["nosuchkind"], "unknown node kind 'nosuchkind'"),
        (["ingest", "--params", "[1]"], "must be a JSON object"),
        (["ingest", "--param", "source=dataset"], "source 'dataset' needs a path"),
    ],
)
def test_bad_usage_exits_2_naming_the_problem(args, words):
    proc = spawn(["-m", "stg_node.nodes", *args])
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 2 and words in out, out


def test_the_node_stops_when_its_launcher_goes_away(broker, bus_url, tmp_path):
    """STG_LAUNCH_PID names a parent that is not ours: the node takes the launcher for gone."""
    env_pid = os.getpid() + 1_000_000  # never our parent
    proc = spawn(
        ["-m", "stg_node.nodes", "tests.nodes.sample_nodes:Echo", "--bus", bus_url],
        env=child_env(STG_LAUNCH_PID=str(env_pid)),
    )
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0 and "launcher (pid" in out, out
