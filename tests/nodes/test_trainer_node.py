"""The trainer node on a fake avatar: pairing, bounded buffers, metrics, snapshots, checkpoints, resume."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
from nodehelpers import NodeThread, recv_until, wait_until
from sample_nodes import pose

from stg_node.bus import Bus, BusConfig, Frame, GaussianSnapshot, NodeStatus, Subscriber, TrainerMetrics
from stg_node.nodes.avatar_adapter import TrainerAdapter
from stg_node.nodes.params import parse_params
from stg_node.nodes.trainer import FramePairs, TrainerNode, TrainerParams

FAKE = "tests.nodes.fake_avatar"


def frame(index: int, value: int = 100) -> Frame:
    image = np.full((8, 8, 3), value, np.uint8)
    mask = np.full((8, 8), 255, np.uint8)
    return Frame(index=index, image=image, mask=mask, K=np.eye(3), R=np.eye(3), t=np.array([0.0, 0.0, 3.0]))


def test_frame_pairs_match_in_either_order_and_stay_bounded():
    pairs = FramePairs(limit=4)
    f = frame(3)
    f.header.seq = 10
    p = pose(3)
    p.frame_seq = 10
    assert pairs.add_frame(f) is None and pairs.add_pose(p) == (f, p)
    assert pairs.add_pose(p) is None and pairs.add_frame(f) == (f, p)
    for i in range(100):  # an endless stream of poses whose frames never come
        q = pose(i)
        q.frame_seq = 1000 + i
        pairs.add_pose(q)
    assert len(pairs.poses) == 4 and len(pairs.frames) == 0


def trainer(bus_url, **params) -> TrainerNode:
    return TrainerNode(
        "trainer", parse_params(TrainerParams, {"avatar": FAKE, **params}), BusConfig(url=bus_url)
    )


def feed(feeder: Bus, start: int, count: int, value: int = 100) -> None:
    for topic in ("camera/frame", "body/pose"):
        assert feeder.publisher.wait_for_subscribers(topic, 10)
    for i in range(start, start + count):
        seq = feeder.publish(frame(i, value))
        p = pose(i)
        p.frame_seq = seq
        feeder.publish(p)
        time.sleep(0.01)


def test_metrics_snapshots_checkpoints_and_resume(broker, bus_url, tmp_path, monkeypatch):
    ckpt, out = tmp_path / "ckpt", tmp_path / "out"
    params = {
        "iters": 30,
        "snapshot_every": 10,
        "snapshot_every_s": 0,
        "checkpoint_dir": str(ckpt),
        "out": str(out),
        "eval_data": str(tmp_path),
    }
    with Subscriber(BusConfig(url=bus_url), ["trainer/metrics", "avatar/snapshot"]) as sub:
        with Bus(bus_url, node="feeder", heartbeat_s=0) as feeder:
            node = trainer(bus_url, **params)
            with NodeThread(node) as run:
                feed(feeder, 0, 3, value=60)
                run.thread.join(60)
                assert run.code == 0
            seen: list = []  # until the last of each (on two lanes: either may come first)
            assert recv_until(
                sub, lambda m: isinstance(m, GaussianSnapshot) and m.model_version == 30, 30, seen
            )
            if not any(isinstance(m, TrainerMetrics) and m.iteration == 30 for m in seen):
                assert recv_until(
                    sub, lambda m: isinstance(m, TrainerMetrics) and m.iteration == 30, 30, seen
                )
            metrics = [m for m in seen if isinstance(m, TrainerMetrics)]
            snapshots = [m for m in seen if isinstance(m, GaussianSnapshot)]
            assert [m.iteration for m in metrics] == list(range(1, 31))
            assert metrics[-1].loss == 1 / 31 and metrics[-1].extra["frames_added"] >= 1
            assert [s.model_version for s in snapshots] == [10, 20, 30]
            assert all(isinstance(s, GaussianSnapshot) for s in snapshots)
            np.testing.assert_allclose(snapshots[-1].arrays["color"], [[60 / 255] * 3], rtol=1e-6)
            summary = json.loads((out / "summary.json").read_text())
            assert summary["iterations"] == 30 and summary["finished"]
            # The fake's step k has PSNR 10 + 0.01 k: the summary's is the mean over the steps done.
            assert summary["psnr"] == pytest.approx(10 + 0.01 * 15.5)
            assert summary["psnr_last_step"] == pytest.approx(10.30)
            assert "mean over the last 30 steps" in summary["psnr_note"]
            assert summary["heldout"] == {"split": "novel_view", "views": 4, "psnr": 20.03, "ssim": 0.5,
                                          "lpips": 0.1}  # fmt: skip

            # respawned (stg-launch says so): continues from the checkpoint, not from 0
            monkeypatch.setenv("STG_RESPAWN", "1")
            node = trainer(bus_url, **{**params, "iters": 45})
            with NodeThread(node) as run:
                feed(feeder, 3, 3)
                run.thread.join(60)
                assert run.code == 0
            seen = []
            assert recv_until(sub, lambda m: isinstance(m, TrainerMetrics) and m.iteration == 45, 30, seen)
            resumed = [m.iteration for m in seen if isinstance(m, TrainerMetrics)]
    assert resumed == list(range(31, 46))
    summary = json.loads((out / "summary.json").read_text())
    assert summary["iterations"] == 45 and summary["resumed_from"] == str(ckpt / "trainer.ckpt")
    assert summary["elapsed_s"] > 0


def test_a_fresh_start_ignores_an_old_checkpoint_unless_asked(bus_url, tmp_path, monkeypatch):
    from fake_avatar import TrainConfig, Trainer

    monkeypatch.delenv("STG_RESPAWN", raising=False)
    old = Trainer(TrainConfig())
    old.iteration = 17
    old.notes = {"elapsed_s": 3.0}
    old.save(str(tmp_path / "trainer.ckpt"))
    for resume, expected in (("respawn", 0), ("always", 17), ("never", 0)):
        node = trainer(bus_url, checkpoint_dir=str(tmp_path), resume=resume)
        try:
            node.setup()
            assert node.iteration == expected, resume
            assert (node.resumed_from is not None) == (expected > 0)
            assert node.elapsed_before == (3.0 if expected else 0.0)  # from the same file
        finally:
            node.bus.close()


def test_a_stopped_trainer_flushes_a_final_snapshot_and_checkpoint(broker, bus_url, tmp_path):
    node = trainer(bus_url, checkpoint_dir=str(tmp_path), snapshot_every_s=0, checkpoint_every_s=0)
    with Subscriber(BusConfig(url=bus_url), ["avatar/snapshot"]) as sub:
        with Bus(bus_url, node="feeder", heartbeat_s=0) as feeder, NodeThread(node) as run:
            feed(feeder, 0, 2)
            assert wait_until(lambda: node.iteration > 5, timeout=30)
            assert run.stop() == 0
        snap = recv_until(sub, lambda m: m.model_version == node.iteration, 30)
    assert snap is not None and snap.model_version == node.iteration > 0
    saved = TrainerAdapter.load(tmp_path / "trainer.ckpt", module=FAKE)  # the one file the node writes
    assert saved.iteration == node.iteration and saved.notes["elapsed_s"] > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["trainer.ckpt"]


def test_a_refused_pose_keeps_its_frame_out_in_either_order():
    pairs = FramePairs(limit=4)
    for order in ("frame first", "pose first"):
        f, p = frame(3), pose(3)
        f.header.seq = p.frame_seq = 20 if order == "frame first" else 21
        if order == "frame first":
            assert pairs.add_frame(f) is None
            pairs.reject(p)
        else:
            pairs.reject(p)
            assert pairs.add_frame(f) is None
        assert not pairs.frames and not pairs.rejected, order
    for i in range(100):  # refusals of frames that never come stay bounded too
        q = pose(i)
        q.frame_seq = 500 + i
        pairs.reject(q)
    assert len(pairs.rejected) == 4


def test_frames_tracked_with_low_confidence_never_reach_the_avatar(broker, bus_url):
    """Unsure frames are bright, sure ones dark: the fake avatar's colour (the mean of the frames it
    holds) shows which reached it."""
    # preset slow: a step takes 50 ms, so metrics come at 20 Hz, not in a flood that could
    # overflow the subscriber's queue while the test waits for the node
    node = trainer(bus_url, preset="slow", min_confidence=0.6, snapshot_every_s=0, metrics_every=1)
    with Subscriber(BusConfig(url=bus_url), ["trainer/metrics", "avatar/snapshot", "node/status"]) as sub:
        with Bus(bus_url, node="feeder", heartbeat_s=0) as feeder, NodeThread(node) as run:
            for topic in ("camera/frame", "body/pose"):
                assert feeder.publisher.wait_for_subscribers(topic, 10)
            for i in range(8):
                sure = i % 2 == 0
                seq = feeder.publish(frame(i, 60 if sure else 250))
                p = pose(i)
                p.frame_seq, p.confidence = seq, (0.9 if sure else 0.3)
                feeder.publish(p)
                # one pair at a time: camera/frame is keep-last, so a pair sent while the node is
                # busy may replace the one before it (a counted drop, not what this test is about)
                assert wait_until(lambda n=i + 1: node.frames_added + node.frames_unsure == n, timeout=30)
            assert node.frames_added == 4 and node.frames_unsure == 4
            assert run.stop() == 0
        # The node has stopped: wait for what it said last. Its final snapshot (published at the
        # stop), the metrics of its last step (a step always follows the frame that was added last)
        # and its last heartbeat (sent as it stops, with the final counts).
        final = node.iteration
        messages: list = []

        def said(what):  # read before (on another lane), or still to come
            return next((m for m in messages if what(m)), None) or recv_until(sub, what, 30, messages)

        snapshot = said(lambda m: isinstance(m, GaussianSnapshot))
        metrics = said(lambda m: isinstance(m, TrainerMetrics) and m.iteration == final)
        status = said(lambda m: isinstance(m, NodeStatus) and m.node == "trainer" and m.state == "stopping")
    assert snapshot is not None and snapshot.model_version == final
    assert metrics is not None, f"no trainer/metrics for iteration {final}"
    assert status is not None, "no last heartbeat from the trainer"
    np.testing.assert_allclose(snapshot.arrays["color"], [[60 / 255] * 3], rtol=1e-6)
    assert metrics.extra["frames_added"] == 4 and metrics.extra["frames_low_confidence"] == 4
    assert status.drops.get("low_confidence") == 4
