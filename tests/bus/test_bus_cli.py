"""stg-topic list / echo / hz / bw against a running broker, checked against what was published."""

from __future__ import annotations

import io
import re
import threading
import time

import numpy as np
import pytest
from bushelpers import sample_messages, wait_until

from stg_node.bus import Broker, BusConfig, Frame, NodeStatus, Publisher, Subscriber
from stg_node.bus.codec import encode_counted
from stg_node.cli import topic as topic_cli


class Talker:
    """Publishes body/pose every ``period`` s (and camera/frame every 3rd time) in a thread,
    recording when each pose went out: the truth for hz."""

    def __init__(self, url: str, period: float = 0.02):
        self.config = BusConfig(url=url)
        self.period = period
        self.stamps: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        pose = sample_messages()["BodyPose"]
        frame = Frame(index=0, image=np.zeros((4, 4, 3), np.uint8), K=np.eye(3), R=np.eye(3), t=np.zeros(3))
        with Publisher(self.config, node="talker") as pub:
            i = 0
            next_time = time.monotonic()
            while not self._stop.is_set():
                pub.publish(pose)
                self.stamps.append(time.monotonic())
                if i % 3 == 0:
                    pub.publish(frame)
                i += 1
                next_time += self.period
                self._stop.wait(max(0.0, next_time - time.monotonic()))

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join(5)


@pytest.fixture
def running(ipc_url):
    with Broker(ipc_url, status_period_s=0.2), Talker(ipc_url) as talker:
        yield ipc_url, talker


def _run(*argv) -> str:
    out = io.StringIO()
    assert topic_cli.main(list(argv), out=out) == 0
    return out.getvalue()


def test_list_shows_topics_types_lanes_and_sources(running):
    url, _ = running
    text = _run("--bus", url, "list", "--duration", "1.0")
    rows = {line.split()[0]: line.split() for line in text.splitlines()[1:] if line.strip()}
    assert rows["body/pose"][1:3] == ["BodyPose", "reliable"] and rows["body/pose"][-1] == "talker"
    assert rows["camera/frame"][1:3] == ["Frame", "latest"]
    assert rows["node/status"][1] == "NodeStatus" and rows["node/status"][-1] == "broker"
    assert float(rows["body/pose"][4]) > 10  # ~50 Hz published


def test_echo_prints_header_fields_and_array_summaries(running):
    url, _ = running
    text = _run("--bus", url, "echo", "body/pose", "-n", "2")
    blocks = text.split("--- ")[1:]
    assert len(blocks) == 2
    assert blocks[0].startswith("body/pose  BodyPose v1  seq ")
    assert "src talker" in blocks[0]
    assert "frame_seq: 3" in blocks[0] and "confidence: 0.9" in blocks[0]
    poses = sample_messages()["BodyPose"].poses
    assert f"poses: float32[24, 3]  min {poses.min():.4g}  max {poses.max():.4g}" in blocks[0]


def test_hz_matches_the_rate_actually_published(running):
    """The rate stg-topic hz reports over its whole run against the talker's own send times over
    the same run (a window larger than the run: the same messages on both sides)."""
    url, talker = running
    assert wait_until(lambda: len(talker.stamps) > 10, 30)  # the talker is under way
    start = time.monotonic()
    text = _run("--bus", url, "hz", "body/pose", "--duration", "2.0", "--window", "10000")
    end = time.monotonic()
    reported = float(re.findall(r"average rate: ([\d.]+) Hz", text)[-1])
    stamps = [t for t in list(talker.stamps) if start <= t <= end]
    truth = (len(stamps) - 1) / (stamps[-1] - stamps[0])
    assert reported == pytest.approx(truth, rel=0.25)
    assert "window: " in text


def test_hz_and_the_brokers_node_status_report_the_same_rate(running):
    """Live: what stg-topic hz prints and what the broker's NodeStatus says for the same topic."""
    url, talker = running
    rates: list[float] = []
    stop = threading.Event()

    def watch():
        with Subscriber(BusConfig(url=url), ["node/status"]) as sub:
            while not stop.is_set():
                msg = sub.recv(timeout=0.2)
                if isinstance(msg, NodeStatus) and msg.node == "broker" and "body/pose" in msg.rates_hz:
                    rates.append(msg.rates_hz["body/pose"])

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    try:
        assert wait_until(lambda: len(talker.stamps) > 10, 30)  # the talker is under way
        text = _run("--bus", url, "hz", "body/pose", "--duration", "2.0", "--window", "10000")
    finally:
        stop.set()
        watcher.join(5)
    reported = float(re.findall(r"average rate: ([\d.]+) Hz", text)[-1])
    # body/pose crosses the broker only while someone subscribes (hz, for 2 s): its reports then
    assert len(rates) >= 3, rates
    assert reported == pytest.approx(np.median(rates[1:]), rel=0.25)


def test_bw_reports_the_exact_message_size(running):
    url, _ = running
    text = _run("--bus", url, "bw", "body/pose", "-n", "20")
    _, nbytes = encode_counted(
        sample_messages()["BodyPose"], topic="body/pose", seq=5, src="talker", stamp_ns=time.time_ns()
    )
    mean = re.findall(r"mean: (\d+)B", text)[-1]
    assert int(mean) == nbytes
    assert re.search(r"average: [\d.]+KB/s", text)


def test_bad_bus_url_is_a_clear_error(capsys):
    assert topic_cli.main(["--bus", "http://nope", "list"]) == 2
    assert "ipc:///path" in capsys.readouterr().err


def test_nothing_on_the_bus(ipc_url):
    with Broker(ipc_url, status_period_s=0):
        assert "no messages" in _run("--bus", ipc_url, "list", "--duration", "0.3")
        assert "no messages on body/pose" in _run("--bus", ipc_url, "hz", "body/pose", "--duration", "0.3")


def test_bus_options_work_before_and_after_the_subcommand(running):
    url, _ = running
    before = _run("--bus", url, "echo", "body/pose", "-n", "1")
    after = _run("echo", "body/pose", "-n", "1", "--bus", url)
    assert before.startswith("--- body/pose") and after.startswith("--- body/pose")
