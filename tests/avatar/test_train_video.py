"""``stg-train --format video``: a plain video becomes an avatar (tracked first, cached), and its
options and failures: --intrinsics / --fov only with a video, exit codes 1 and 2."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from fixtures.videos import count_tracking_runs, synthetic_clip

from stg_node.cli import render as render_cli
from stg_node.cli import train as train_cli
from tests.tracking.trackhelpers import needs_blazepose

FAST = ["--preset", "fast", "--size", "128", "--no-progress"]


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return synthetic_clip(tmp_path_factory.mktemp("video") / "clip", frames=12, blank=3)


@pytest.fixture(autouse=True)
def _private_track_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("STG_TRACK_CACHE", str(tmp_path / "track-cache"))


def test_camera_options_belong_to_videos_and_bad_input_exits_1(tmp_path, clip, monkeypatch, capsys):
    out = str(tmp_path / "run")
    for argv in (
        ["--data", str(clip.subject), "--format", "synthetic", "--out", out, "--fov", "60"],
        [
            "--data",
            str(clip.video),
            "--format",
            "video",
            "--out",
            out,
            "--fov",
            "60",
            "--intrinsics",
            "k.json",
        ],
        ["--data", str(clip.video), "--format", "video", "--out", out, "--fov", "400"],
    ):
        assert train_cli.main(argv) == 2, argv
    capsys.readouterr()
    assert train_cli.main(["--data", str(tmp_path / "none.mp4"), "--format", "video", "--out", out]) == 1
    assert "no such video file" in capsys.readouterr().err
    bad = tmp_path / "bad.json"
    bad.write_text('{"K": [[100, 0, 9000], [0, 100, 50], [0, 0, 1]]}')
    assert (
        train_cli.main(
            ["--data", str(clip.video), "--format", "video", "--out", out, "--intrinsics", str(bad)]
        )
        == 1
    )
    assert "principal point" in capsys.readouterr().err
    monkeypatch.setenv("STG_POSE_MODELS", str(tmp_path / "no-networks"))
    assert train_cli.main(["--data", str(clip.video), "--format", "video", "--out", out, *FAST]) == 1
    err = capsys.readouterr().err
    assert err.startswith("stg-train: error: ") and "install_pose_models" in err and "Traceback" not in err


@needs_blazepose
def test_a_video_becomes_an_avatar_with_two_commands(tmp_path, clip, monkeypatch):
    calls = count_tracking_runs(monkeypatch)
    run = tmp_path / "run"
    argv = ["--data", str(clip.video), "--format", "video", "--out", str(run), "--iters", "6",
            "--intrinsics", str(clip.calibration), *FAST]  # fmt: skip
    assert train_cli.main(argv) == 0
    summary = json.loads((run / "summary.json").read_text())
    assert summary["finished"] and summary["iterations"] == 6 and summary["gaussians"] > 0
    # The tracked video as a folder dataset: the subject's frames, not the black ones after them.
    data = run / "video_data"
    cameras = json.loads((data / "cameras.json").read_text())["cameras"]
    np.testing.assert_allclose(cameras["camera"]["K"], json.loads(clip.calibration.read_text())["K"])
    kept = sorted(int(p.stem) for p in (data / "images" / "camera").glob("*.jpg"))
    assert set(kept) <= set(range(clip.frames)) and len(kept) >= clip.frames - 2, kept
    assert sorted(int(p.stem) for p in (data / "masks" / "camera").glob("*.png")) == kept
    config = json.loads((run / "config.json").read_text())
    assert config["data"]["format"] == "video" and config["data"]["root"] == str(data.resolve())
    assert summary["frames"] == len(kept)
    # Before training: the fit preview (a frame per input frame) and what was skipped, and why.
    preview = cv2.VideoCapture(str(run / "fit_preview.mp4"))
    assert int(preview.get(cv2.CAP_PROP_FRAME_COUNT)) == clip.frames + clip.blank
    tracking = summary["tracking"]
    assert tracking["kept"] == len(kept) and tracking["skipped"] == clip.frames + clip.blank - len(kept)
    assert tracking["skipped_by_reason"].get("no_person", 0) >= clip.blank  # the black frames
    assert tracking["camera"]["method"] == "file"
    assert config["config"]["lr_pose"] > 1e-4 and config["config"]["loss"]["pose_smooth"] > 0  # tracked poses

    # The second command: the avatar, rendered.
    video = tmp_path / "avatar.mp4"
    assert render_cli.main([str(run), "-o", str(video), "--frames", "2", "--no-progress"]) == 0
    assert video.stat().st_size > 0

    # Training on: the tracking comes from the cache.
    assert train_cli.main([*argv[: -len(FAST)], "--iters", "8", "--resume", *FAST]) == 0
    assert len(calls) == 1 and json.loads((run / "summary.json").read_text())["iterations"] == 8
