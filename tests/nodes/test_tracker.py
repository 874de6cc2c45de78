"""The tracker node: the dataset's SMPL fits matched to frames by index and time; the estimator protocol."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from fixtures.datasets import write_thuman4, write_zju_original
from nodehelpers import NodeThread, taken, wait_until

from stg_node.bus import Bus, BusConfig, Frame, Subscriber
from stg_node.bus.messages import NodeStatus
from stg_node.data.types import SmplParams
from stg_node.nodes.convert import pose_message
from stg_node.nodes.params import ParamError, parse_params
from stg_node.nodes.tracker import (
    EstimateMismatch,
    PoseEstimate,
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
    estimate = estimator.estimate(frame(2, 2 / dataset.fps))
    np.testing.assert_allclose(estimate.smpl.poses, truth.smpl[2]["poses"], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(estimate.smpl.Th, truth.smpl[2]["Th"], rtol=1e-6, atol=1e-6)
    assert estimate.confidence == 1.0 and estimate.mask is None
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
            for n, i in enumerate([0, 1, 2, 1]):
                f = frame(i, i / fps)
                seq = ingest.publish(f, stamp_ns=1_000 + i)
                sent.append((i, seq))
                # the keep-last lane: one frame at a time
                assert wait_until(lambda n=n: taken(node, "camera/frame") == n + 1, 30)
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

            assert wait_until(done, timeout=60, step=0)
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
            ingest.publish(frame(99, 0.0))  # the estimator finds nobody: no pose
            assert wait_until(lambda: taken(node, "camera/frame") == 1, 30)
            ingest.publish(frame(3, 0.1))
            got = sub.recv(timeout=30)
    assert got is not None and got.frame_index == 3 and got.confidence == 0.5 and got.Th[0] == 2.0


def test_thuman4_smplx_fits_are_replayed_as_the_nearest_smpl_parameters(tmp_path, caplog):
    """BodyPose refuses SMPL-X numbers; the replay sends the shared joints with SMPL's mean shape."""
    truth = write_thuman4(tmp_path / "t", num_frames=3, num_cams=1)
    dataset = open_replay_dataset(str(tmp_path / "t"), "thuman4")
    assert dataset.smpl(1).model == "smplx"
    with pytest.raises(ValueError, match="smplx"):
        pose_message(dataset.smpl(1))  # what the node used to drop every THuman4.0 frame on
    estimator = ReplayEstimator(dataset, log=logging.getLogger("test"))
    with caplog.at_level(logging.WARNING):
        estimates = [estimator.estimate(frame(i, i / dataset.fps)) for i in range(3)]
    assert sum("SMPLX fits" in r.getMessage() for r in caplog.records) == 1  # said once
    for i, estimate in enumerate(estimates):
        smpl = estimate.smpl
        assert smpl.model == "smpl" and np.array_equal(smpl.betas, np.zeros(10, np.float32))
        np.testing.assert_allclose(smpl.poses[:22], truth.smpl[i]["poses"][:22], atol=1e-6)
        assert not smpl.poses[22:].any()
        np.testing.assert_allclose(smpl.Th, truth.smpl[i]["Th"], atol=1e-6)
        assert pose_message(smpl).to_smpl().model == "smpl"


class Masking:
    """A live estimator that also segments: the mask is the left half of the frame; frame 5 fails,
    frame 6 answers in a form no estimator may use, frame 7 with a plain (smpl, confidence) pair."""

    def estimate(self, frame):
        z = np.zeros(3, np.float32)
        smpl = SmplParams(poses=np.zeros((24, 3), np.float32), Rh=z, Th=z, betas=np.zeros(10, np.float32))
        if frame.index == 5:
            raise RuntimeError("the network gave up")
        if frame.index == 6:
            return "a pose"
        if frame.index == 7:
            return smpl, 0.25
        mask = np.zeros(frame.image.shape[:2], np.uint8)
        mask[:, : frame.image.shape[1] // 2] = 255
        return PoseEstimate(smpl, 0.75, mask)


def test_the_tracker_republishes_frames_with_their_mask_and_the_pose_names_them(broker, bus_url):
    params = parse_params(
        TrackerParams,
        {"mode": "live", "estimator": "tests.nodes.test_tracker:Masking", "input_topic": "raw/camera/frame",
         "frame_topic": "camera/frame", "latest_only": "false"},
    )  # fmt: skip
    node = TrackerNode("tracker", params, BusConfig(url=bus_url), heartbeat_s=0.1)
    topics = ["body/pose", "camera/frame", "node/status"]
    with Subscriber(BusConfig(url=bus_url), topics, keep_last=False) as sub, NodeThread(node):
        with Bus(bus_url, node="ingest", heartbeat_s=0) as ingest:
            assert ingest.publisher.wait_for_subscribers("raw/camera/frame", 10)
            for n, i in enumerate((3, 5, 6, 7, 4)):
                raw = frame(i, i / 30)
                raw.image = np.full((4, 6, 3), i, np.uint8)
                ingest.publish(raw, "raw/camera/frame", stamp_ns=5_000 + i)
                # the keep-last lane: one frame at a time
                assert wait_until(lambda n=n: taken(node, "raw/camera/frame") == n + 1, 30)
            poses, frames, drops = [], {}, {}

            def done():
                msg = sub.recv(timeout=0.2)
                if isinstance(msg, NodeStatus):
                    drops.update(msg.drops if msg.node == "tracker" else {})
                elif isinstance(msg, Frame):
                    frames[msg.header.seq] = msg
                elif msg is not None:
                    poses.append(msg)
                return len(poses) == 3 and drops.get("estimator_error") == 2

            assert wait_until(done, timeout=60, step=0), (poses, drops)
    assert [(p.frame_index, p.confidence) for p in poses] == [(3, 0.75), (7, 0.25), (4, 0.75)]
    for p in poses:
        sent = frames[p.frame_seq]  # the pose names the republished frame
        assert sent.header.src == "tracker" and sent.index == p.frame_index
        assert sent.header.stamp_ns == p.header.stamp_ns == 5_000 + p.frame_index
        assert np.all(sent.image == p.frame_index) and sent.image.shape == (4, 6, 3)
    assert frames[poses[0].frame_seq].mask[:, :3].all() and not frames[poses[0].frame_seq].mask[:, 3:].any()
    assert frames[poses[1].frame_seq].mask is None  # a pair carries no mask; the frame had none


def test_live_params_refuse_a_loop_and_a_bad_estimator_name():
    with pytest.raises(ParamError, match="loop"):
        parse_params(TrackerParams, {"mode": "live", "frame_topic": "camera/frame"})
    with pytest.raises(ParamError, match="package.module:Class"):
        parse_params(TrackerParams, {"mode": "live", "estimator": "nocolon"})
    assert parse_params(TrackerParams, {"mode": "live"}).estimator == ""  # the built-in one
