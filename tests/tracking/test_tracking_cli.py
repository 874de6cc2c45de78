"""``stg-track`` and ``track_video``: the POSES.npz contract, exit codes, masks, the cache."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from fixtures.videos import count_tracking_runs, write_video
from tiny_onnx import dot_heatmap_model
from trackhelpers import needs_blazepose

from stg_node.body import load_smpl_params
from stg_node.cli.track import main
from stg_node.tracking import pipeline
from stg_node.tracking.poses_file import PosesFileError, read_poses

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def synth_video(tmp_path_factory, synth_small):
    frames = [cv2.imread(str(p))[..., ::-1] for p in sorted((synth_small.folder / "Camera_B1").glob("*.png"))]
    return write_video(tmp_path_factory.mktemp("video") / "clip.avi", frames[:12])


@pytest.fixture(scope="module")
def dot_model(tmp_path_factory):
    path = tmp_path_factory.mktemp("onnx") / "dots.onnx"
    dot_heatmap_model(path)
    return path


def test_usage_errors_exit_with_2(tmp_path, capsys):
    for argv in (
        [],
        [str(tmp_path / "missing.mp4"), "--out", str(tmp_path / "p.npz")],
        [str(tmp_path), "--out", str(tmp_path / "p.txt")],
        [str(tmp_path), "--out", str(tmp_path / "p.npz"), "--fov", "60", "--intrinsics", "k.json"],
        [str(tmp_path), "--out", str(tmp_path / "p.npz"), "--detector", "onnx"],
        [str(tmp_path), "--out", str(tmp_path / "p.npz"), "--mask-method", "plate"],
    ):
        assert main(argv) == 2, argv
    assert "usage: stg-track" in capsys.readouterr().err


def test_missing_networks_exit_with_1_and_name_the_fix(tmp_path, monkeypatch, synth_video, capsys):
    monkeypatch.setenv("STG_POSE_MODELS", str(tmp_path / "empty"))
    assert main([str(synth_video), "--out", str(tmp_path / "p.npz"), "--no-progress"]) == 1
    error = capsys.readouterr().err
    assert error.startswith("stg-track: error: ") and "install_pose_models" in error
    assert not (tmp_path / "p.npz").exists()


def test_poses_file_contract_with_any_detector(tmp_path, synth_video, dot_model, synth_small):
    """The ONNX dot network finds no body, but the file must still hold every frame, validly."""
    out = tmp_path / "POSES.npz"
    masks = tmp_path / "masks"
    code = main(
        [str(synth_video), "--out", str(out), "--masks", str(masks), "--detector", "onnx", "--pose-model",
         str(dot_model), "--mask-method", "mog2", "--fov", "40", "--no-progress"]
    )  # fmt: skip
    assert code == 0
    with np.load(out) as npz:
        assert npz["poses"].shape == (12, 72) and npz["poses"].dtype == np.float32
        assert npz["Rh"].shape == (12, 3) and npz["Th"].shape == (12, 3)
        assert npz["shapes"].shape == (12, 10) and npz["confidence"].shape == (12,)
        assert np.all((npz["confidence"] >= 0) & (npz["confidence"] <= 1))
        assert np.all(npz["poses"][:, :3] == 0)
        assert npz["K"][0, 0] == pytest.approx((256 / 2) / np.tan(np.radians(20)))
    assert sorted(p.name for p in masks.iterdir())[:2] == ["000000.png", "000001.png"]
    assert len(list(masks.iterdir())) == 12
    motion = load_smpl_params(out)  # the body package's own reader takes it as a motion
    assert motion.poses.shape == (12, 24, 3) and motion.fps == pytest.approx(30.0)
    assert np.allclose(motion.betas, np.load(out)["shapes"])
    tracked = read_poses(out)
    assert tracked.image_size == (256, 256) and len(tracked) == 12


def test_stg_track_runs_as_a_module(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    result = subprocess.run(
        [sys.executable, "-m", "stg_node.cli.track", "--help"],
        capture_output=True,
        text=True,
        env=env,
        cwd=ROOT,
    )
    assert result.returncode == 0 and "POSES.npz" in result.stdout


def test_broken_poses_files_are_refused(tmp_path):
    path = tmp_path / "p.npz"
    np.savez(
        path, poses=np.zeros((3, 72)), Rh=np.zeros((3, 3)), Th=np.zeros((3, 3)), shapes=np.zeros((3, 10))
    )
    with pytest.raises(PosesFileError, match="confidence"):
        read_poses(path)
    np.savez(
        path, poses=np.zeros((3, 72)), Rh=np.zeros((2, 3)), Th=np.zeros((3, 3)), shapes=np.zeros((3, 10)),
        confidence=np.ones(3),
    )  # fmt: skip
    with pytest.raises(PosesFileError, match="Rh"):
        read_poses(path)


def test_track_video_caches_by_content_and_options(tmp_path, monkeypatch, synth_video, dot_model):
    calls = count_tracking_runs(monkeypatch)
    options = pipeline.TrackOptions(detector="onnx", pose_model=str(dot_model), mask="none")
    cache = tmp_path / "cache"
    first = pipeline.track_video(synth_video, options, cache_dir=cache, progress=False)
    again = pipeline.track_video(synth_video, options, cache_dir=cache, progress=False)
    assert first == again and first.name == "POSES.npz" and len(calls) == 1
    assert len(list((first.parent / "masks").iterdir())) == 12
    wider = pipeline.TrackOptions(detector="onnx", pose_model=str(dot_model), mask="none", fov_deg=50.0)
    other = pipeline.track_video(synth_video, wider, cache_dir=cache, progress=False)
    assert other != first and len(calls) == 2
    copy = tmp_path / "copy.avi"
    copy.write_bytes(synth_video.read_bytes())
    assert pipeline.track_video(copy, options, cache_dir=cache, progress=False) == first  # same bytes
    assert len(calls) == 2
    assert not [p for p in cache.iterdir() if p.name.startswith(".")]  # no staging folders left


def test_track_video_retracks_after_a_code_change(tmp_path, monkeypatch, request, synth_video, dot_model):
    """An edited fit or keypoint layout must not be answered from a cache entry the old code wrote."""
    calls = count_tracking_runs(monkeypatch)
    options = pipeline.TrackOptions(detector="onnx", pose_model=str(dot_model), mask="none")
    cache = tmp_path / "cache"
    first = pipeline.track_video(synth_video, options, cache_dir=cache, progress=False)
    package = tmp_path / "pkg"
    (package / "tracking").mkdir(parents=True)
    source = package / "tracking" / "fitting.py"
    source.write_text("WEIGHT = 1.0\n")
    monkeypatch.setattr(pipeline.stg_node, "__file__", str(package / "__init__.py"))
    digest = pipeline.tracking_code_digest
    request.addfinalizer(digest.cache_clear)  # no digest of the stand-in package outlives the test
    before = digest(("tracking",))
    source.write_text("WEIGHT = 0.5\n")
    digest.cache_clear()
    after = digest(("tracking",))
    assert before != after
    monkeypatch.setattr(pipeline, "tracking_code_digest", lambda: after)
    edited = pipeline.track_video(synth_video, options, cache_dir=cache, progress=False)
    assert edited != first and len(calls) == 2


@needs_blazepose
def test_stg_track_on_a_synthetic_video_with_the_shipped_detector(tmp_path, synth_video, synth_small):
    import json

    intrinsics = tmp_path / "K.json"
    intrinsics.write_text(json.dumps({"K": synth_small.K.tolist()}))
    out = tmp_path / "POSES.npz"
    assert main([str(synth_video), "--out", str(out), "--intrinsics", str(intrinsics), "--no-progress"]) == 0
    tracked = read_poses(out)
    assert np.median(tracked.confidence) > 0.6
    assert np.allclose(tracked.K, synth_small.K)
    # The person stands about 3.5 m in front of the camera.
    assert np.all((tracked.Th[:, 2] > 2.5) & (tracked.Th[:, 2] < 4.5))


def test_video_to_folder_gives_a_folder_dataset_of_the_confident_frames(tmp_path, synth_video, dot_model):
    import json

    from stg_node.data import open_dataset

    options = pipeline.TrackOptions(detector="onnx", pose_model=str(dot_model), mask="mog2")
    cache = tmp_path / "cache"
    with pytest.raises(ValueError, match="no frame was tracked"):  # the dot network finds nobody
        pipeline.video_to_folder(synth_video, tmp_path / "none", options, cache_dir=cache, progress=False)
    # Pretend the tracker was sure about every other frame: only those become training views.
    poses = pipeline.track_video(synth_video, options, cache_dir=cache, progress=False)
    with np.load(poses) as npz:
        data = dict(npz)
    data["confidence"] = np.where(np.arange(12) % 2 == 0, 0.9, 0.1).astype(np.float32)
    np.savez(poses, **data)
    out = pipeline.video_to_folder(synth_video, tmp_path / "data", options, cache_dir=cache, progress=False)
    report = json.loads((out / pipeline.TRACKING_REPORT).read_text())
    assert (report["kept"], report["skipped"]) == (6, 6)
    expected: dict[str, int] = {}  # the reasons the tracker gave the frames left out
    for i in range(1, 12, 2):
        for why in [w for w in str(data["flags"][i]).split(",") if w] or ["low_confidence"]:
            expected[why] = expected.get(why, 0) + 1
    assert report["skipped_by_reason"] == expected and sum(expected.values()) >= 6
    dataset = open_dataset(out, kind="folder", split="all", size=None)
    assert dataset.frames == [0, 2, 4, 6, 8, 10] and len(dataset) == 6
    sample = dataset[1]
    assert sample.index == 2 and sample.image.shape == (256, 256, 3) and sample.mask.shape == (256, 256)
    assert np.allclose(sample.camera.K, data["K"]) and np.allclose(sample.smpl.Th, data["Th"][2])


@needs_blazepose
def test_a_sure_estimate_refits_to_the_first_pass_masks(tmp_path, synth_video, monkeypatch, capsys):
    """A sure focal estimate: the tracking is re-fitted with it, the keypoints and the first pass's
    person masks (the silhouette term, as the first pass fitted), and the report says so."""
    import json

    from stg_node.tracking import focal

    sure = focal.FocalEstimate(
        focal_px=128 / np.tan(np.radians(25.0)), fov_deg=50.0, low_fov_deg=48.0, high_fov_deg=52.0,
        sure=True, reason="the interval spans +-4 %", frames=24, rise=0.03,
    )  # fmt: skip
    monkeypatch.setattr(focal, "estimate_focal", lambda *a, **k: sure)
    refits = []
    first_pass = pipeline._first_pass_silhouette

    def recorded(tracker, masks_dir, index):
        silhouette = first_pass(tracker, masks_dir, index)
        refits.append(None if silhouette is None else int((silhouette(None) > 127).sum()))
        return silhouette

    monkeypatch.setattr(pipeline, "_first_pass_silhouette", recorded)
    out = tmp_path / "POSES.npz"
    assert main([str(synth_video), "--out", str(out), "--no-progress"]) == 0
    assert refits and all(r is not None for r in refits) and max(refits) > 100, refits
    assert "50.0 degree field of view estimated from the footage" in capsys.readouterr().out
    tracked = read_poses(out)
    camera = json.loads(tracked.camera)
    assert camera["used"] == "estimate" and camera["sure"]
    assert tracked.K[0, 0] == pytest.approx(128 / np.tan(np.radians(25.0)))


@needs_blazepose
def test_stg_track_reports_skips_and_camera_and_writes_the_preview(tmp_path, synth_video, capsys):
    """No calibration, no field of view: the focal length is estimated (12 frames are too few: unsure,
    the default kept, said so); the preview has one frame per input frame."""
    import json

    out, preview = tmp_path / "POSES.npz", tmp_path / "fit.mp4"
    assert main([str(synth_video), "--out", str(out), "--preview", str(preview), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "skipped" in printed and "camera: UNSURE" in printed and "fit preview" in printed
    assert "trains with the estimate" in printed  # the flag that takes the estimate anyway
    tracked = read_poses(out)
    camera = json.loads(tracked.camera)
    assert camera["method"] == "estimate" and camera["used"] == "default" and not camera["sure"]
    assert tracked.K[0, 0] == pytest.approx(128 / np.tan(np.radians(65 / 2)))
    assert tracked.flags.shape == (12,)
    cap = cv2.VideoCapture(str(preview))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 12
    ok, frame = cap.read()
    assert ok and frame.shape[:2] == (256, 256)
