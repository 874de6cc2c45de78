"""The ingest node: datasets replayed with their calibration and masks, pacing, video/V4L2 and OAK paths."""

from __future__ import annotations

import time
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from fixtures.datasets import write_thuman4, write_zju_original
from nodehelpers import NodeThread
from sample_nodes import pose

from stg_node.bus import Bus, BusConfig, Frame, Subscriber
from stg_node.data import open_dataset
from stg_node.nodes import ingest as ingest_module
from stg_node.nodes.ingest import IngestNode, IngestParams
from stg_node.nodes.params import parse_params
from stg_node.nodes.sources import Calibration, OakSource, OpenCVSource, SourceError

# Every frame, in order: camera/frame moved to the lossless lane, as a replay launch file may do.
LOSSLESS = {"camera/frame": "reliable"}


def ingest(bus_url, **params) -> IngestNode:
    config = BusConfig(url=bus_url, lanes=LOSSLESS)
    return IngestNode("ingest", parse_params(IngestParams, params), config, heartbeat_s=0.2)


def collect(bus_url, node: IngestNode, count: int, timeout: float = 60.0) -> list[Frame]:
    frames = []
    config = BusConfig(url=bus_url, lanes=LOSSLESS)
    with Subscriber(config, ["camera/frame"]) as sub, NodeThread(node) as run:
        deadline = time.monotonic() + timeout
        while len(frames) < count and time.monotonic() < deadline:
            msg = sub.recv(timeout=1)
            if msg is not None:
                frames.append(msg)
        run.stop()
    return frames


@pytest.mark.parametrize("layout", ["zju", "thuman4"])
def test_dataset_frames_carry_the_datasets_images_masks_and_calibration(broker, bus_url, tmp_path, layout):
    root = tmp_path / layout
    (write_zju_original if layout == "zju" else write_thuman4)(root, num_frames=3, num_cams=2)
    truth = open_dataset(root, split="all", size=64)
    node = ingest(bus_url, path=str(root), split="all", size=64, rate_hz=100, wait_subscribers_s=30)
    frames = collect(bus_url, node, len(truth))
    assert len(frames) == len(truth)
    for msg, ref in zip(frames, truth.views, strict=True):
        sample = truth.load(ref.frame, ref.camera)
        assert (msg.index, msg.camera_id) == (sample.index, sample.camera.name)
        assert msg.time == pytest.approx(sample.time)
        np.testing.assert_array_equal(msg.image, sample.image)
        np.testing.assert_array_equal(msg.mask, sample.mask)
        np.testing.assert_allclose(msg.K, sample.camera.K)
        np.testing.assert_allclose(msg.R, sample.camera.R)
        np.testing.assert_allclose(msg.t, sample.camera.t)


def test_a_set_rate_paces_the_frames(broker, bus_url, tmp_path, monkeypatch):
    """rate_hz 20: frame k goes out at k / 20 s. Checked on the node's own clock, replaced here by
    one that only moves when the node sleeps, so a busy machine cannot change the answer (the
    real-time rate is a benchmark's business)."""
    write_zju_original(tmp_path / "d", num_frames=8, num_cams=1)
    node = ingest(bus_url, path=str(tmp_path / "d"), size=32, rate_hz=20, wait_subscribers_s=0)
    clock = [100.0]

    def sleep(seconds: float) -> bool:
        clock[0] += max(0.0, seconds)
        return True

    monkeypatch.setattr(ingest_module, "time", SimpleNamespace(monotonic=lambda: clock[0]))
    monkeypatch.setattr(node, "sleep", sleep)
    sent = []
    publish = node.publish
    monkeypatch.setattr(
        node, "publish", lambda msg, **kw: (sent.append((clock[0], msg.index)), publish(msg, **kw))
    )
    assert node.execute() == 0
    assert [i for _, i in sent] == list(range(8))
    np.testing.assert_allclose([t for t, _ in sent], 100.0 + 0.05 * np.arange(8), atol=1e-9)


def test_as_fast_as_consumed_waits_for_acknowledgements(broker, bus_url, tmp_path):
    """rate_hz 0: frame k is published only after body/pose acknowledged frame k - 1 - max_ahead."""
    write_zju_original(tmp_path / "d", num_frames=6, num_cams=1)
    node = ingest(
        bus_url, path=str(tmp_path / "d"), size=32, rate_hz=0, max_ahead=0, pace_timeout_s=30, loop=True
    )
    config = BusConfig(url=bus_url, lanes=LOSSLESS)
    seen = []
    with Subscriber(config, ["camera/frame"]) as sub, Bus(bus_url, node="acker", heartbeat_s=0) as acker:
        with NodeThread(node):
            for k in range(10):
                msg = sub.recv(timeout=30)
                assert msg is not None and msg.header.seq == k
                seen.append(msg.index)
                assert sub.recv(timeout=0.3) is None  # nothing more until acknowledged
                ack = pose(msg.index)
                ack.frame_seq = msg.header.seq
                acker.publish(ack)
    assert seen == [0, 1, 2, 3, 4, 5, 0, 1, 2, 3]  # looped


def test_video_files_go_through_the_v4l2_reader(tmp_path):
    """OpenCVSource reads a file with the code a V4L2 camera uses (only the open call differs)."""
    path = tmp_path / "clip.avi"
    colors = [(255, 0, 0), (0, 255, 0), (0, 0, 255), (200, 200, 40)]  # RGB
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48))
    for rgb in colors:
        writer.write(np.full((48, 64, 3), rgb[::-1], np.uint8))  # OpenCV writes BGR
    writer.release()
    source = OpenCVSource(str(path), v4l2=False, hfov_deg=90.0)
    frames = list(source.frames())
    assert [f.index for f in frames] == [0, 1, 2, 3]
    for f, rgb in zip(frames, colors, strict=True):
        np.testing.assert_allclose(f.image.reshape(-1, 3).mean(axis=0), rgb, atol=6)
    assert frames[1].time == pytest.approx(0.1)
    assert frames[0].camera.K[0, 0] == pytest.approx(32.0)  # f = (W/2) / tan(45 deg)
    with pytest.raises(SourceError, match="cannot open V4L2 device"):
        OpenCVSource("/dev/video-none", v4l2=True)


def test_calibration_files_are_read_and_checked(tmp_path):
    good = tmp_path / "cal.json"
    good.write_text('{"K": [[500, 0, 320], [0, 500, 240], [0, 0, 1]], "t": [0, 0, 2]}')
    cal = Calibration.from_file(good)
    assert cal.K[0, 2] == 320 and cal.t[2] == 2 and (cal.R == np.eye(3)).all()
    bad = tmp_path / "bad.json"
    bad.write_text('{"K": [1, 2]}')
    with pytest.raises(SourceError, match="bad.json: not a calibration file"):
        Calibration.from_file(bad)


def test_oak_frames_through_depthais_host_side_replay(tmp_path):
    """The OAK source's reader on depthai's ReplayVideo node (runs on the host: no device)."""
    path = tmp_path / "clip.mp4"
    colors = [(250, 10, 10), (10, 250, 10), (10, 10, 250)]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10, (64, 48))
    for rgb in colors:
        for _ in range(2):
            writer.write(np.full((48, 64, 3), rgb[::-1], np.uint8))
    writer.release()
    source = OakSource(replay=str(path), width=64, height=48, fps=30)
    frames = list(source.frames())
    assert len(frames) == 6 and [f.index for f in frames] == list(range(6))
    for f, rgb in zip(frames[::2], colors, strict=True):
        assert f.image.shape == (48, 64, 3)
        np.testing.assert_allclose(f.image.reshape(-1, 3).mean(axis=0), rgb, atol=12)  # RGB, not BGR
    with pytest.raises(SourceError, match="does not exist"):
        OakSource(replay=str(tmp_path / "none.mp4"))


def test_a_missing_dataset_fails_setup_with_the_path(broker, bus_url, tmp_path, caplog):
    node = ingest(bus_url, path=str(tmp_path / "nowhere"))
    assert node.execute() == 1  # the launcher sees exit code 1
    assert f"{tmp_path / 'nowhere'}: is not a folder" in caplog.text
