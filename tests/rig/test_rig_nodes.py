"""A rig on the bus: the rig ingest (cameras read together, stamped at capture, undistorted, one
topic each), the tracker pairing the cameras by stamp and publishing a frame and a pose per camera,
the trainer reading every camera's topic, and the launch file."""

from __future__ import annotations

import json
import time

import cv2
import numpy as np
import pytest
from nodehelpers import ROOT, NodeThread, wait_until

from stg_node.body.params import SmplParams
from stg_node.bus import Bus, BusConfig, Frame, NodeStatus, Subscriber
from stg_node.calibration.rig import Rig, RigCamera, write_rig
from stg_node.nodes.ingest import IngestNode, IngestParams
from stg_node.nodes.params import ParamError, parse_params
from stg_node.nodes.rig import RigEstimate, camera_topic
from stg_node.nodes.rig_sources import RigSource
from stg_node.nodes.sources import SourceError
from stg_node.nodes.tracker import TrackerNode, TrackerParams
from stg_node.nodes.trainer import TrainerNode, TrainerParams

SIZE = (64, 48)


def rig_file(tmp_path, distorted: bool = True):
    K = np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])
    side = cv2.Rodrigues(np.array([0.0, np.pi / 2, 0.0]))[0]
    cameras = (
        RigCamera("front", K, np.array([-0.2, 0.05, 0, 0, 0]) if distorted else np.zeros(0), np.eye(3),
                  np.array([0.0, 0.0, 3.0]), SIZE),
        RigCamera("side", K, np.zeros(0), side, np.array([0.1, 0.0, 3.0]), SIZE),
    )  # fmt: skip
    return write_rig(tmp_path / "rig.json", Rig(cameras))


def video(path, count, fps=20.0, base=0):
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, SIZE)
    for i in range(count):
        image = np.zeros((SIZE[1], SIZE[0], 3), np.uint8)
        image[:, :] = (base + 10 * i) % 256
        cv2.rectangle(image, (10 + i, 10), (30 + i, 30), (255, 255, 255), -1)
        writer.write(image)
    writer.release()
    return str(path)


def test_a_cameras_topic_puts_its_name_before_the_standard_name():
    assert camera_topic("camera/frame", "front") == "front/camera/frame"
    assert camera_topic("raw/camera/frame", "side") == "raw/side/camera/frame"
    assert camera_topic("/rig1/camera/frame", "a") == "/rig1/a/camera/frame"


def test_the_rig_source_reads_every_camera_stamped_and_undistorted(tmp_path):
    rig = rig_file(tmp_path)
    files = [video(tmp_path / "front.avi", 8), video(tmp_path / "side.avi", 8, base=5)]
    source = RigSource(str(rig), files, v4l2=False)
    frames = list(source.frames())
    by_camera = {name: [f for f in frames if f.camera.name == name] for name in ("front", "side")}
    assert [f.index for f in by_camera["front"]] == list(range(8)) == [f.index for f in by_camera["side"]]
    for a, b in zip(by_camera["front"], by_camera["side"], strict=True):
        assert abs(a.stamp_ns - b.stamp_ns) < 1_000_000  # played together from one start: one instant
    steps = np.diff([f.stamp_ns for f in by_camera["front"]])
    np.testing.assert_allclose(steps, 50_000_000, atol=2_000_000)  # 20 fps, stamped by the file's times
    # The front camera's frames come undistorted with its lens; K, R, t are the rig's.
    raw = cv2.VideoCapture(files[0])
    ok, bgr = raw.read()
    camera = source.rig["front"]
    expected = cv2.cvtColor(cv2.undistort(bgr, camera.K, camera.dist), cv2.COLOR_BGR2RGB)
    inner = (slice(8, -8), slice(8, -8))
    assert np.abs(by_camera["front"][0].image[inner].astype(int) - expected[inner]).mean() < 2.0
    assert (
        np.abs(
            by_camera["front"][0].image[inner].astype(int) - cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)[inner]
        ).mean()
        > 2.0
    )
    np.testing.assert_allclose(by_camera["side"][0].camera.R, source.rig["side"].R)
    np.testing.assert_allclose(by_camera["front"][0].camera.K, camera.K)


def test_the_rig_source_refuses_wrong_counts_and_sizes(tmp_path):
    rig = rig_file(tmp_path)
    with pytest.raises(SourceError, match="1 videos for the rig's 2 cameras"):
        RigSource(str(rig), [video(tmp_path / "a.avi", 2)], v4l2=False)
    big = tmp_path / "big.avi"
    writer = cv2.VideoWriter(str(big), cv2.VideoWriter_fourcc(*"MJPG"), 20.0, (80, 60))
    writer.write(np.zeros((60, 80, 3), np.uint8))
    writer.release()
    with pytest.raises(SourceError, match="delivers 80x60 frames, but the rig is calibrated at 64x48"):
        list(RigSource(str(rig), [str(big), str(big)], v4l2=False).frames())
    with pytest.raises(ParamError, match="rig needs rig"):
        parse_params(IngestParams, {"source": "rig", "videos": "a.avi"})


def test_the_ingest_publishes_each_camera_on_its_own_topic(broker, bus_url, tmp_path):
    rig = rig_file(tmp_path)
    files = ",".join([video(tmp_path / "front.avi", 6), video(tmp_path / "side.avi", 6)])
    params = parse_params(IngestParams, {"source": "rig", "rig": str(rig), "videos": files})
    node = IngestNode("ingest", params, BusConfig(url=bus_url), remap={"camera/frame": "raw/camera/frame"})
    topics = ["raw/front/camera/frame", "raw/side/camera/frame"]
    got = {t: [] for t in topics}
    with Subscriber(BusConfig(url=bus_url), topics, keep_last=False) as sub, NodeThread(node):

        def done():
            msg = sub.recv(timeout=0.2)
            if msg is not None:
                got[msg.header.topic].append(msg)
            return all(len(v) == 6 for v in got.values())

        assert wait_until(done, timeout=30, step=0), {t: len(v) for t, v in got.items()}
    assert {m.camera_id for m in got[topics[1]]} == {"side"}
    for a, b in zip(got[topics[0]], got[topics[1]], strict=True):
        assert a.index == b.index and abs(a.header.stamp_ns - b.header.stamp_ns) < 1_000_000


class Counting:
    """A rig estimator for the node tests: confidence from the set's first index, a mask per view."""

    def __init__(self):
        self.sets = []

    def estimate_set(self, frames):
        self.sets.append([f.index for f in frames])
        Th = np.array([0.0, 0.0, float(frames[0].index)])
        smpl = SmplParams(poses=np.zeros((24, 3)), Rh=np.zeros(3), Th=Th, betas=np.zeros(10))
        confidence = 0.1 if frames[0].index == 7 else 0.9
        return RigEstimate(smpl, confidence, [np.full(f.image.shape[:2], 255, np.uint8) for f in frames])


def raw_frame(index, camera):
    return Frame(index=index, time=index / 30, camera_id=camera, image=np.full((4, 6, 3), index, np.uint8),
                 K=np.eye(3), R=np.eye(3), t=np.zeros(3))  # fmt: skip


def test_the_tracker_pairs_the_cameras_by_stamp_and_publishes_a_frame_and_pose_each(
    broker, bus_url, tmp_path
):
    rig = rig_file(tmp_path)
    params = parse_params(
        TrackerParams,
        {"mode": "live", "rig": str(rig), "estimator": "tests.rig.test_rig_nodes:Counting",
         "input_topic": "raw/camera/frame", "frame_topic": "camera/frame", "latest_only": "false",
         "min_confidence": 0.5, "sync_tolerance_s": 0.01},
    )  # fmt: skip
    node = TrackerNode("tracker", params, BusConfig(url=bus_url), heartbeat_s=0.1)
    out_topics = [
        "front/body/pose",
        "side/body/pose",
        "front/camera/frame",
        "side/camera/frame",
        "node/status",
    ]
    ms = 1_000_000
    with Subscriber(BusConfig(url=bus_url), out_topics, keep_last=False) as sub, NodeThread(node):
        with Bus(bus_url, node="ingest", heartbeat_s=0) as ingest:
            for name in ("front", "side"):
                assert ingest.publisher.wait_for_subscribers(f"raw/{name}/camera/frame", 10)
            # instant 3: both cameras 4 ms apart; instant 4: side 30 ms late (no pair for front's
            # frame 4, but side's frame pairs with front's 5); instant 7: low confidence
            sends = [("front", 3, 1000), ("side", 3, 1004), ("front", 4, 1033), ("front", 5, 1066),
                     ("side", 4, 1063), ("front", 7, 1200), ("side", 7, 1201)]  # fmt: skip
            for camera, index, at in sends:
                ingest.publish(raw_frame(index, camera), f"raw/{camera}/camera/frame", stamp_ns=at * ms)
                time.sleep(0.05)
            poses, frames, drops = [], {}, {}

            def done():
                msg = sub.recv(timeout=0.2)
                if isinstance(msg, NodeStatus):
                    drops.update(msg.drops if msg.node == "tracker" else {})
                elif isinstance(msg, Frame):
                    frames[(msg.camera_id, msg.header.seq)] = msg
                elif msg is not None:
                    poses.append(msg)
                return len(poses) == 4 and drops.get("low_confidence") == 1

            assert wait_until(done, timeout=15, step=0), (poses, drops)
    # Two sets: (front 3, side 3) and (front 5, side 4); one instant, one index: the first camera's.
    assert [(p.frame_index, float(p.Th[2])) for p in poses] == [(3, 3.0), (3, 3.0), (5, 5.0), (5, 5.0)]
    # A camera's pose names the frame on that camera's topic (seqs count per topic).
    sent = [frames[(p.header.topic.split("/")[0], p.frame_seq)] for p in poses]
    assert [p.header.topic for p in poses] == ["front/body/pose", "side/body/pose"] * 2
    assert [f.camera_id for f in sent] == ["front", "side", "front", "side"]
    assert [f.index for f in sent] == [3, 3, 5, 5] and sent[3].image[0, 0, 0] == 4  # side's own image
    assert all(f.mask is not None and f.mask.all() for f in sent)
    assert sent[1].header.topic == "side/camera/frame"


def test_the_trainer_reads_every_camera_of_the_rig(broker, bus_url, tmp_path):
    rig = rig_file(tmp_path)
    params = parse_params(TrainerParams, {"avatar": "tests.nodes.fake_avatar", "rig": str(rig), "iters": 0})
    node = TrainerNode("trainer", params, BusConfig(url=bus_url), heartbeat_s=0.1)
    from sample_nodes import pose

    with NodeThread(node):
        with Bus(bus_url, node="tracker", heartbeat_s=0) as feeder:
            for name in ("front", "side"):
                assert feeder.publisher.wait_for_subscribers(f"{name}/camera/frame", 10)
                assert feeder.publisher.wait_for_subscribers(f"{name}/body/pose", 10)
            added = 0
            for i in range(3):
                for name in ("front", "side"):  # the same seq on both cameras' topics
                    f = raw_frame(i, name)
                    f.mask = np.full((4, 6), 255, np.uint8)
                    seq = feeder.publish(f, f"{name}/camera/frame")
                    p = pose(i)
                    p.frame_seq = seq
                    feeder.publish(p, f"{name}/body/pose")
                    added += 1
                    # keep-last lanes: the next frame once this one is in (as a subscriber reads them)
                    assert wait_until(lambda n=added: node.frames_added == n, timeout=15), (i, name)
    assert node.frames_added == 6


def test_the_rig_launch_file_validates_and_is_documented(tmp_path):
    from stg_node.launch.spec import read_launch

    spec = read_launch(
        ROOT / "launch" / "rig_v4l2.yaml", {"calibration": str(tmp_path / "rig.json"), "devices": "0,2"}
    )
    ingest, tracker, trainer = spec.node("ingest"), spec.node("tracker"), spec.node("trainer")
    assert ingest.params.source == "rig" and ingest.params.devices == "0,2"
    assert tracker.params.rig == trainer.params.rig == str(tmp_path / "rig.json")
    assert tracker.params.sync_tolerance_s == pytest.approx(0.02)
    assert "rig_v4l2.yaml" in (ROOT / "docs" / "LAUNCH.md").read_text()
    assert "rig_v4l2.yaml" in (ROOT / "docs" / "RIGS.md").read_text()


@pytest.mark.slow
def test_the_rig_launch_on_videos_tracks_and_trains_from_every_camera(tmp_path):
    """stg-launch launch/rig_v4l2.yaml videos:=... (no cameras): three synthetic cameras played together,
    the multi-view tracker, the trainer (the tests' stand-in avatar) learning from all three."""
    from nodehelpers import run_launch

    from stg_node.tracking.evaluation import write_video
    from stg_node.tracking.rig_evaluation import synth_rig

    subject = tmp_path / "subject"
    from stg_node.data.synth.generate import SynthConfig, generate

    generate(SynthConfig(out=subject, seed=5, num_frames=30, size=256, num_novel_views=5, view_every=1000,
                         train_cameras=(0, 2, 4), supersample=1), progress=False)  # fmt: skip
    names = ["1", "3", "5"]
    videos = [
        write_video(sorted((subject / f"Camera_B{c}").glob("*.png")), tmp_path / f"{c}.avi", 10.0)
        for c in names
    ]
    rig = write_rig(tmp_path / "rig.json", synth_rig(subject, names))
    out = tmp_path / "out"
    args = [
        str(ROOT / "launch" / "rig_v4l2.yaml"),
        f"calibration:={rig}",
        f"videos:={','.join(map(str, videos))}",
    ]
    args += [f"out:={out}", f"bus:=ipc://{tmp_path}/bus", "iters:=30", "max_side:=256"]
    run = run_launch([*args, "avatar:=tests.nodes.fake_avatar"], timeout=400)
    assert run.code == 0, run.log[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["iterations"] == 30 and summary["frames_added"] >= 3, summary
