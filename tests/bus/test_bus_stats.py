"""Rates: a node's heartbeat (NodeStatus) and stg-topic hz/bw/list compute them with the same code
(bus.stats) and agree on the same stream; each checked against numbers computed here by hand."""

from __future__ import annotations

import numpy as np
import pytest
import zmq

from stg_node.bus import BodyPose, BusConfig, Heartbeat, Publisher, Subscriber
from stg_node.bus.stats import ArrivalWindow, RateMeter, TopicCensus, per_second


class FakeClock:
    def __init__(self, now: float = 100.0):
        self.now = now

    def __call__(self) -> float:
        return self.now


def _pose(num_betas: int) -> BodyPose:
    return BodyPose(
        poses=np.zeros((24, 3), np.float32),
        Rh=np.zeros(3, np.float32),
        Th=np.zeros(3, np.float32),
        betas=np.zeros(num_betas, np.float32),  # varies the message size
    )


def test_heartbeat_rates_and_the_hz_window_agree_on_the_same_stream():
    """Real messages through a publisher and subscriber; the arrival times are ours (irregular
    gaps), fed to the heartbeat's clock and to stg-topic's window alike."""
    rng = np.random.default_rng(3)
    n = 40
    times = 50.0 + np.concatenate([[0.0], np.cumsum(rng.uniform(0.005, 0.08, n - 1))])
    clock = FakeClock(times[0] - 1.0)
    config = BusConfig(url="inproc://stats-agree")
    ctx = zmq.Context()
    try:
        with (
            Publisher(config, node="talker", context=ctx, bind=True) as talker,
            Publisher(config, node="listener", context=ctx, lanes=["reliable"]) as own,
            Subscriber(config, ["body/pose"], context=ctx, typed=False, keep_last=False) as sub,
        ):
            assert talker.wait_for_subscribers("body/pose")
            heartbeat = Heartbeat(own, [sub], period_s=1.0, clock=clock)  # not started: we sample it
            window = ArrivalWindow(size=n - 1)  # exactly the stream's n - 1 gaps
            sizes = []
            for i, t in enumerate(times):
                talker.publish(_pose(1 + i % 7))
                env = sub.recv(timeout=30.0)
                assert env is not None
                clock.now = t
                window.add(t, env.nbytes)
                sizes.append(env.nbytes)
                if i == 0:
                    heartbeat.status()  # the heartbeat's interval starts at the first arrival
            status = heartbeat.status()
    finally:
        ctx.destroy(linger=0)
    stats = window.stats()
    span = times[-1] - times[0]
    truth_hz = (n - 1) / span
    truth_bw = sum(sizes[1:]) / span  # the bytes that arrived after the interval began
    assert len(set(sizes)) == 7
    assert status.received == {"body/pose": n}
    assert status.rates_hz["body/pose"] == pytest.approx(stats.rate_hz, rel=1e-12)
    assert status.bytes_per_s["body/pose"] == pytest.approx(stats.bytes_per_s, rel=1e-12)
    assert stats.rate_hz == pytest.approx(truth_hz, rel=1e-12)
    assert stats.bytes_per_s == pytest.approx(truth_bw, rel=1e-12)


def test_rate_meter_counts_only_the_interval_since_the_last_sample():
    clock = FakeClock(10.0)
    meter = RateMeter(clock)
    clock.now = 12.0
    first = meter.sample({"a": 10, "b": 4}, {"a": 1000, "b": 40})
    assert first.rates_hz == {"a": 5.0, "b": 2.0} and first.bytes_per_s == {"a": 500.0, "b": 20.0}
    assert first.interval_s == 2.0
    clock.now = 12.5
    second = meter.sample({"a": 11, "b": 4, "c": 3}, {"a": 1100, "b": 40, "c": 30})
    assert second.rates_hz == {"a": 2.0, "b": 0.0, "c": 6.0}
    assert second.bytes_per_s == {"a": 200.0, "b": 0.0, "c": 60.0}
    same_instant = meter.sample({"a": 12}, {"a": 1200})  # no time passed: finite, not a crash
    assert np.isfinite(same_instant.rates_hz["a"])


def test_arrival_window_statistics_match_numpy():
    rng = np.random.default_rng(0)
    arrivals = np.cumsum(rng.uniform(0.01, 0.05, 300))
    sizes = rng.integers(100, 5000, 300)
    window = ArrivalWindow(size=50)
    for t, nbytes in zip(arrivals, sizes, strict=True):
        window.add(float(t), int(nbytes))
    stats = window.stats()
    last = arrivals[-51:]  # 51 arrival times: 50 gaps
    gaps = np.diff(last)
    assert stats.arrivals == 51 and window.received == 300
    assert stats.rate_hz == pytest.approx(50 / (last[-1] - last[0]), rel=1e-12)
    assert stats.min_gap_s == pytest.approx(gaps.min()) and stats.max_gap_s == pytest.approx(gaps.max())
    assert stats.std_gap_s == pytest.approx(np.std(gaps), rel=1e-9)
    assert stats.bytes_per_s == pytest.approx(sizes[-50:].sum() / (last[-1] - last[0]), rel=1e-12)
    assert stats.mean_bytes == pytest.approx(sizes[-50:].mean())
    assert (stats.min_bytes, stats.max_bytes, stats.sized) == (sizes[-50:].min(), sizes[-50:].max(), 50)


def test_arrival_window_before_two_messages_and_bad_size():
    window = ArrivalWindow(size=5)
    assert window.stats() is None
    window.add(1.0, 10)
    assert window.stats() is None and len(window) == 1
    window.add(1.5, 30)
    stats = window.stats()
    assert stats.rate_hz == 2.0 and stats.bytes_per_s == 60.0 and stats.std_gap_s == 0.0
    with pytest.raises(ValueError, match="at least 1"):
        ArrivalWindow(size=0)


def test_topic_census_counts_rates_sizes_and_sources():
    census = TopicCensus(max_topics=2, max_sources=2)
    for i in range(10):
        census.add("body/pose", "BodyPose", 100 + i, f"src{i % 3}")
    census.add("camera/frame", "Frame", 5000, "ingest")
    census.add("made/up", "Custom", 1, "x")  # over max_topics: counted as <other>
    rows = {row.topic: row for row in census.summary(seconds=2.0)}
    assert list(rows) == ["<other>", "body/pose", "camera/frame"]
    pose = rows["body/pose"]
    assert pose.messages == 10 and pose.rate_hz == per_second(10, 2.0) == 5.0
    assert pose.mean_bytes == pytest.approx(104.5)
    assert pose.sources == ("<other>", "src0", "src1")  # a third source name is bounded too
    assert rows["<other>"].messages == 1
