"""The live pipeline from a plain video: ingest (video file) -> tracker (live: BlazePose + SMPL fit +
mask) -> trainer -> renderer, checked against the synthetic subject the video was rendered from.

The fast test runs the four nodes in threads with the stand-in avatar (tests/nodes/fake_avatar.py);
the slow ones run launch/live_v4l2.yaml (the real avatar) and launch/live_oak.yaml (depthai's
host-side replay) through stg-launch, as a user without a camera would.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from fixtures.videos import truth_mask, truth_smpl
from nodehelpers import ROOT, NodeThread, run_launch, wait_until

from stg_node.bus import BusConfig, Frame, Subscriber
from stg_node.bus.messages import BodyPose, NodeStatus, RenderedImage, TrainerMetrics
from stg_node.nodes.ingest import IngestNode, IngestParams
from stg_node.nodes.params import parse_params
from stg_node.nodes.renderer import RendererNode, RendererParams
from stg_node.nodes.tracker import TrackerNode, TrackerParams
from stg_node.nodes.trainer import TrainerNode, TrainerParams
from tests.tracking.trackhelpers import needs_blazepose

pytestmark = needs_blazepose

FAKE = "tests.nodes.fake_avatar"
RAW = "raw/camera/frame"


def _iou(mask: np.ndarray, truth: np.ndarray) -> float:
    ours = mask > 0
    return float((ours & truth).sum() / max(1, (ours | truth).sum()))


def _joint_errors(body, poses: list[BodyPose], subject) -> tuple[np.ndarray, np.ndarray]:
    """Per pose: pelvis distance to the truth (m) and mean joint error after aligning the pelvis (m),
    both in the world frame (the camera's R, t came from the calibration file)."""
    from stg_node.tracking.evaluation import joints_from_params

    def joints(params):
        return joints_from_params(
            body,
            np.stack([p.poses.reshape(72) for p in params]),
            np.stack([p.Rh for p in params]),
            np.stack([p.Th for p in params]),
            np.stack([p.betas for p in params]),
        )

    ours = joints([p.to_smpl() for p in poses])
    truth = joints([truth_smpl(subject, p.frame_index) for p in poses])
    pelvis = np.linalg.norm(ours[:, 0] - truth[:, 0], axis=1)
    aligned = np.linalg.norm((ours - ours[:, :1]) - (truth - truth[:, :1]), axis=2).mean(axis=1)
    return pelvis, aligned


def test_a_video_through_the_live_pipeline_gives_poses_masks_and_avatar_images(broker, bus_url, clip):
    """Every pose names a republished frame that carries the person mask; poses are in the world of
    the frame's camera; frames of nobody get confidence 0 and never reach the trainer; the renderer
    serves images of what the trainer learned."""
    from stg_node.body import load_body_model

    config = BusConfig(url=bus_url)
    tracker = TrackerNode(
        "tracker",
        parse_params(
            TrackerParams,
            {
                "mode": "live",
                "estimator_params": {"max_side": "256"},
                "input_topic": RAW,
                "frame_topic": "camera/frame",
            },
        ),  # fmt: skip
        config,
        heartbeat_s=0.2,
    )
    trainer = TrainerNode(
        "trainer",
        parse_params(
            TrainerParams,
            {
                "avatar": FAKE,
                "preset": "slow",
                "snapshot_every_s": 0.3,
                "metrics_every": 5,
                "min_confidence": 0.5,
            },
        ),
        config,
        heartbeat_s=0.2,
    )
    renderer = RendererNode(
        "renderer",
        parse_params(
            RendererParams, {"avatar": FAKE, "default_view": "train", "size": 64, "idle_rate_hz": 5}
        ),
        config,
        heartbeat_s=0,
    )
    frames_total = 2 * (clip.frames + clip.blank)  # two passes: the loop back to frame 0 is a cut
    ingest = IngestNode(
        "ingest",
        parse_params(
            IngestParams,
            {
                "source": "video",
                "path": str(clip.video),
                "calibration": str(clip.calibration),
                # as fast as the tracker takes them, one at a time (each after the pose of the one
                # before): a busy machine slows the test down instead of dropping frames
                "rate_hz": 0,
                "max_ahead": 0,
                "pace_timeout_s": 10,
                "loop": True,
                "max_frames": frames_total,
                "wait_subscribers_s": 30,
            },
        ),  # fmt: skip
        config,
        remap={"camera/frame": RAW},
        heartbeat_s=0,
    )
    topics = ["body/pose", "camera/frame", "avatar/image", "node/status", "trainer/metrics"]
    poses, frames, images, drops, metrics = [], {}, [], {}, []
    with Subscriber(config, topics, keep_last=False) as sub:
        with NodeThread(tracker), NodeThread(trainer), NodeThread(renderer), NodeThread(ingest) as feeding:

            def collect() -> bool:
                msg = sub.recv(timeout=0.2)
                if isinstance(msg, BodyPose):
                    poses.append(msg)
                elif isinstance(msg, Frame):
                    frames[msg.header.seq] = msg
                elif isinstance(msg, RenderedImage):
                    images.append(msg)
                elif isinstance(msg, TrainerMetrics):
                    metrics.append(msg)
                elif isinstance(msg, NodeStatus) and msg.node == "trainer":
                    drops.update(msg.drops)
                return (
                    not feeding.thread.is_alive()
                    and drops.get("low_confidence", 0) >= 1
                    and any(i.snapshot_version >= 1 for i in images)
                )

            assert wait_until(collect, timeout=300, step=0), (len(poses), drops, len(images))

            def complete() -> bool:  # what was still on its way: every pose's frame (another lane)
                collect()
                return all(p.frame_seq in frames for p in poses)

            assert wait_until(complete, timeout=60, step=0), [
                p.frame_seq for p in poses if p.frame_seq not in frames
            ]

    # Poses carry a confidence; the subject's frames are tracked, nobody's get zero.
    subject_poses = [p for p in poses if p.frame_index < clip.frames]
    blank_poses = [p for p in poses if p.frame_index >= clip.frames]
    assert len(subject_poses) >= 8 and blank_poses, (len(subject_poses), len(blank_poses))
    assert np.median([p.confidence for p in subject_poses]) > 0.5
    assert all(p.confidence == 0.0 for p in blank_poses)

    # Each pose names the tracker's republished camera/frame, which holds the mask.
    for p in poses:
        frame = frames.get(p.frame_seq)
        assert frame is not None and frame.header.src == "tracker" and frame.index == p.frame_index
        assert frame.mask is not None and frame.mask.shape == (clip.size, clip.size)
        assert frame.header.stamp_ns == p.header.stamp_ns  # both carry the camera's stamp
    ious = [_iou(frames[p.frame_seq].mask, truth_mask(clip.subject, p.frame_index)) for p in subject_poses]
    assert np.median(ious) > 0.85, ious
    assert all(not frames[p.frame_seq].mask.any() for p in blank_poses)

    # In the world of the calibration's camera (3.6 m away, tilted): right to about 10 cm.
    sure = [p for p in subject_poses if p.confidence >= 0.5]
    pelvis, aligned = _joint_errors(load_body_model(), sure, clip.subject)
    assert np.median(pelvis) < 0.2 and np.median(aligned) < 0.15, (pelvis, aligned)

    # The trainer took the confident frames only; the renderer served what it learned.
    assert metrics and metrics[-1].extra["frames_added"] >= 1
    assert metrics[-1].extra["frames_low_confidence"] >= 1
    served = [i for i in images if i.snapshot_version >= 1]
    assert served and served[-1].alpha is not None and served[-1].alpha.any()


def test_live_v4l2_launch_runs_the_pipeline_from_a_video(tmp_path, clip):
    """stg-launch launch/live_v4l2.yaml source:=video, as a user without a camera runs it (the stand-in
    avatar, whose steps take 50 ms): it ends on its own after the iterations, having trained on the
    tracked frames only and rendered the avatar."""
    out = tmp_path / "out"
    run = run_launch(
        [str(ROOT / "launch" / "live_v4l2.yaml"), "source:=video", f"video:={clip.video}",
         f"calibration:={clip.calibration}", f"out:={out}", f"bus:=ipc://{tmp_path}/bus", "iters:=100",
         "max_side:=256", f"avatar:={FAKE}", "preset:=slow"],
        timeout=300,
    )  # fmt: skip
    assert run.code == 0, run.log[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["iterations"] == 100 and summary["finished"], summary
    assert summary["frames_added"] >= 1 and summary["frames_low_confidence"] >= 1, summary
    assert list((out / "frames").glob("*.png")), "the renderer recorded no image"


@pytest.mark.slow
def test_live_v4l2_launch_on_a_video_trains_the_real_avatar_and_renders_it(tmp_path, clip):
    """stg-launch launch/live_v4l2.yaml source:=video: the real STG-Avatar, ending on its own."""
    out, robot = tmp_path / "out", tmp_path / "robot"
    url = f"ipc://{tmp_path}/bus"
    run = run_launch(
        [str(ROOT / "launch" / "live_v4l2.yaml"), "source:=video", f"video:={clip.video}",
         f"calibration:={clip.calibration}", f"out:={out}", f"bus:={url}", "iters:=60", "max_side:=256"],
        timeout=600,
        client_args=["--bus", url, "--out", str(robot), "--count", "3", "--width", "64", "--height", "64",
                     "--timeout", "400"],
        client_timeout=450,
    )  # fmt: skip
    assert run.client_code == 0, run.client_output + run.log[-3000:]
    assert run.code == 0, run.log[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["iterations"] == 60 and summary["finished"] and summary["num_gaussians"] > 0
    assert summary["frames_added"] >= 1 and summary["frames_low_confidence"] >= 1, summary
    records = [json.loads(line) for line in (robot / "images.jsonl").read_text().splitlines()]
    assert len(records) == 3 and all(r["snapshot_version"] >= 1 for r in records)


@pytest.mark.slow
def test_live_oak_launch_replays_a_video_through_depthai(tmp_path, clip):
    """stg-launch launch/live_oak.yaml replay:=FILE (no device): poses and masks flow, the launch ends."""
    out = tmp_path / "out"
    run = run_launch(
        [str(ROOT / "launch" / "live_oak.yaml"), f"replay:={clip.video}", f"width:={clip.size}",
         f"height:={clip.size}", f"out:={out}", f"bus:=ipc://{tmp_path}/bus", "iters:=40",
         "max_side:=256", f"avatar:={FAKE}"],
        timeout=300,
    )  # fmt: skip
    assert run.code == 0, run.log[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["iterations"] == 40 and summary["frames_added"] >= 1, summary
