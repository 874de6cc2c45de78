"""The tracker node: the dataset's SMPL fits matched to frames by index and time; the estimator protocol."""

from __future__ import annotations

import time

import numpy as np
import pytest
from fixtures.datasets import write_zju_original
from nodehelpers import NodeThread, wait_until

from stg_node.bus import Bus, BusConfig, Frame, Subscriber
from stg_node.bus.messages import NodeStatus
from stg_node.data.types import SmplParams
from stg_node.nodes.params import parse_params
from stg_node.nodes.tracker import (
    EstimateMismatch,
    PoseEstimate,
    PoseEstimator,
    ReplayEstimator,
    TrackerNode,
    TrackerParams,
    open_replay_dataset,
)


def frame(index: int, time_s: float) -> Frame:
    return Frame(
        index=index, time=time_s, image=np.zeros((4, 4, 3), np.uint8), K=np.eye(3), R=np.eye(3), t=np.zeros(3)
    )


def test_replay_matches_by_index_and_checks_the_time(tmp_path):
    truth = write_zju_original(tmp_path / "d", num_frames=3, num_cams=1)
    dataset = open_replay_dataset(str(tmp_path / "d"))
    estimator = ReplayEstimator(dataset)
    assert isinstance(estimator, PoseEstimator)
    smpl, confidence = estimator.estimate(frame(2, 2 / dataset.fps))
    np.testing.assert_allclose(smpl.poses, truth.smpl[2]["poses"], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(smpl.Th, truth.smpl[2]["Th"], rtol=1e-6, atol=1e-6)
    assert confidence == 1.0
    with pytest.raises(EstimateMismatch, match="time"):
        estimator.estimate(frame(2, 1.0))
    with pytest.raises(EstimateMismatch, match="not in"):
        estimator.estimate(frame(7, 7 / dataset.fps))


def test_the_node_publishes_a_pose_per_frame_and_counts_mismatches(broker, bus_url, tmp_path):
    truth = write_zju_original(tmp_path / "d", num_frames=3, num_cams=1)
    fps = open_replay_dataset(str(tmp_path / "d")).fps
    params = parse_params(TrackerParams, {"path": str(tmp_path / "d")})
    node = TrackerNode("tracker", params, BusConfig(url=bus_url), heartbeat_s=0.1)
    with Subscriber(BusConfig(url=bus_url), ["body/pose", "node/status"]) as sub, NodeThread(node):
        with Bus(bus_url, node="ingest", heartbeat_s=0) as ingest:
            assert ingest.publisher.wait_for_subscribers("camera/frame", 10)
            sent = []
            for i in [0, 1, 2, 1]:
                f = frame(i, i / fps)
                seq = ingest.publish(f, stamp_ns=1_000 + i)
                sent.append((i, seq))
                time.sleep(0.05)  # the keep-last lane: one frame at a time
            ingest.publish(frame(1, 5.0))  # a frame of some other sequence
            poses, drops = [], {}

            def done():
                msg = sub.recv(timeout=0.2)
                if msg is None:
                    return False
                if isinstance(msg, NodeStatus):
                    if msg.node == "tracker":
                        drops.update(msg.drops)
                else:
                    poses.append(msg)
                return len(poses) == 4 and drops.get("mismatch") == 1

            assert wait_until(done, timeout=15, step=0)
    assert [(p.frame_index, p.frame_seq) for p in poses] == sent
    assert [p.header.stamp_ns for p in poses] == [1_000, 1_001, 1_002, 1_001]  # the frame's stamp
    for p in poses:
        np.testing.assert_allclose(p.Rh, truth.smpl[p.frame_index]["Rh"], rtol=1e-6, atol=1e-6)


class HalfConfident:
    """A live estimator as another package would write one (tests.nodes.test_tracker:HalfConfident)."""

    def __init__(self, shift: float = 0.0):
        self.shift = shift

    def estimate(self, frame):
        if frame.index == 99:
            return None
        z = np.zeros(3, np.float32)
        smpl = SmplParams(
            poses=np.zeros((24, 3), np.float32), Rh=z, Th=z + self.shift, betas=np.zeros(10, np.float32)
        )
        return PoseEstimate(smpl, 0.5)


def test_a_live_estimator_plugs_in_by_name(broker, bus_url):
    params = parse_params(
        TrackerParams,
        {
            "mode": "live",
            "estimator": "tests.nodes.test_tracker:HalfConfident",
            "estimator_params": {"shift": 2.0},
        },
    )
    node = TrackerNode("tracker", params, BusConfig(url=bus_url), heartbeat_s=0)
    with Subscriber(BusConfig(url=bus_url), ["body/pose"]) as sub, NodeThread(node):
        with Bus(bus_url, node="ingest", heartbeat_s=0) as ingest:
            assert ingest.publisher.wait_for_subscribers("camera/frame", 10)
            ingest.publish(frame(99, 0.0))
            time.sleep(0.05)
            ingest.publish(frame(3, 0.1))
            got = sub.recv(timeout=10)
    assert got is not None and got.frame_index == 3 and got.confidence == 0.5 and got.Th[0] == 2.0
