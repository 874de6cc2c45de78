"""The trainer node on a fake avatar: pairing, bounded buffers, metrics, snapshots, checkpoints, resume."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
from nodehelpers import NodeThread, wait_until
from sample_nodes import pose

from stg_node.bus import Bus, BusConfig, Frame, GaussianSnapshot, Subscriber, TrainerMetrics
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
                run.thread.join(30)
                assert run.code == 0
            metrics, snapshots = [], []
            while (msg := sub.recv(timeout=1)) is not None:
                (metrics if isinstance(msg, TrainerMetrics) else snapshots).append(msg)
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
                run.thread.join(30)
                assert run.code == 0
            resumed = [
                m.iteration for m in iter(lambda: sub.recv(timeout=1), None) if isinstance(m, TrainerMetrics)
            ]
    assert resumed == list(range(31, 46))
    summary = json.loads((out / "summary.json").read_text())
    assert summary["iterations"] == 45 and summary["resumed_from"] == str(ckpt / "trainer.ckpt")
    assert summary["elapsed_s"] > 0


def test_a_fresh_start_ignores_an_old_checkpoint_unless_asked(bus_url, tmp_path, monkeypatch):
    from fake_avatar import TrainConfig, Trainer

    monkeypatch.delenv("STG_RESPAWN", raising=False)
    old = Trainer(TrainConfig())
    old.iteration = 17
    old.save(str(tmp_path / "trainer.ckpt"))
    (tmp_path / "trainer.json").write_text('{"iteration": 17, "elapsed_s": 3.0}')
    for resume, expected in (("respawn", 0), ("always", 17), ("never", 0)):
        node = trainer(bus_url, checkpoint_dir=str(tmp_path), resume=resume)
        try:
            node.setup()
            assert node.iteration == expected, resume
            assert (node.resumed_from is not None) == (expected > 0)
        finally:
            node.bus.close()


def test_a_stopped_trainer_flushes_a_final_snapshot_and_checkpoint(broker, bus_url, tmp_path):
    node = trainer(bus_url, checkpoint_dir=str(tmp_path), snapshot_every_s=0, checkpoint_every_s=0)
    with Subscriber(BusConfig(url=bus_url), ["avatar/snapshot"]) as sub:
        with Bus(bus_url, node="feeder", heartbeat_s=0) as feeder, NodeThread(node) as run:
            feed(feeder, 0, 2)
            assert wait_until(lambda: node.iteration > 5, timeout=10)
            assert run.stop() == 0
        snap = sub.recv(timeout=5)
    assert snap is not None and snap.model_version == node.iteration > 0
    assert (tmp_path / "trainer.ckpt").is_file()
    assert json.loads((tmp_path / "trainer.json").read_text())["iteration"] == node.iteration


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
    node = trainer(bus_url, min_confidence=0.6, snapshot_every_s=0, metrics_every=1)
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
                assert wait_until(lambda n=i + 1: node.frames_added + node.frames_unsure == n, timeout=10)
            assert node.frames_added == 4 and node.frames_unsure == 4
            assert run.stop() == 0
        messages, deadline = [], time.monotonic() + 1.0  # the broker's own status never stops
        while time.monotonic() < deadline:
            if (msg := sub.recv(timeout=0.1)) is not None:
                messages.append(msg)
    snapshot = [m for m in messages if isinstance(m, GaussianSnapshot)][-1]
    np.testing.assert_allclose(snapshot.arrays["color"], [[60 / 255] * 3], rtol=1e-6)
    metrics = [m for m in messages if isinstance(m, TrainerMetrics)][-1]
    assert metrics.extra["frames_added"] == 4 and metrics.extra["frames_low_confidence"] == 4
    statuses = [m for m in messages if getattr(m, "node", "") == "trainer"]
    assert statuses and statuses[-1].drops.get("low_confidence") == 4
