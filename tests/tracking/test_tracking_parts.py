"""The tracker's smaller parts: One-Euro smoothing, masks, intrinsics, frame sources, network files."""

from __future__ import annotations

import json
import math
import zipfile

import cv2
import numpy as np
import pytest
import torch

from stg_node.body.lbs import axis_angle_to_matrix
from stg_node.tracking import model_files
from stg_node.tracking.camera import IntrinsicsError, from_fov, load_intrinsics
from stg_node.tracking.masks import BackgroundModelMasker, DepthMasker, clean_mask, make_masker
from stg_node.tracking.smoothing import OneEuroConfig, OneEuroFilter, RotationFilter
from stg_node.tracking.sources import ImageFolderSource, SourceError, VideoSource, open_source

# ---- One-Euro -----------------------------------------------------------------------------------


def _one_euro_reference(values, times, min_cutoff, beta, d_cutoff):
    """The filter of Casiez et al. (2012), scalar, as printed in the paper's pseudo-code."""

    def alpha(cutoff, dt):
        tau = 1.0 / (2 * math.pi * cutoff)
        return 1.0 / (1.0 + tau / dt)

    out, x_prev, dx_prev, t_prev = [], None, 0.0, None
    for x, t in zip(values, times, strict=True):
        if x_prev is None:
            x_prev, t_prev = x, t
            out.append(x)
            continue
        dt = t - t_prev
        dx = (x - x_prev) / dt
        dx_hat = dx_prev + alpha(d_cutoff, dt) * (dx - dx_prev)
        cutoff = min_cutoff + beta * abs(dx_hat)
        x_hat = x_prev + alpha(cutoff, dt) * (x - x_prev)
        out.append(x_hat)
        x_prev, dx_prev, t_prev = x_hat, dx_hat, t
    return np.array(out)


def test_one_euro_matches_the_papers_filter_with_uneven_frame_times():
    rng = np.random.default_rng(0)
    times = np.cumsum(rng.uniform(0.02, 0.05, size=200))
    values = np.sin(times * 3) + rng.normal(0, 0.05, size=200)
    config = OneEuroConfig(min_cutoff_hz=1.2, beta=0.7, derivative_cutoff_hz=1.0)
    f = OneEuroFilter(config)
    ours = np.array([f.filter(np.array([v]), t)[0] for v, t in zip(values, times, strict=True)])
    assert np.allclose(ours, _one_euro_reference(values, times, 1.2, 0.7, 1.0), atol=1e-12)


def test_one_euro_removes_jitter_at_rest_and_follows_fast_motion():
    rng = np.random.default_rng(1)
    times = np.arange(300) / 30.0
    still = 1.0 + rng.normal(0, 0.01, size=300)
    f = OneEuroFilter()
    smoothed = np.array([f.filter(np.array([v]), t)[0] for v, t in zip(still, times, strict=True)])
    assert np.std(smoothed[30:]) < 0.5 * np.std(still[30:])  # at least halved
    ramp = times * 3.0  # 3 units per second
    f = OneEuroFilter()
    followed = np.array([f.filter(np.array([v]), t)[0] for v, t in zip(ramp, times, strict=True)])
    assert np.abs(followed[60:] - ramp[60:]).max() < 0.1  # less than 1 frame of lag


def test_rotation_filter_does_not_wrap_through_the_quaternion_sign():
    # A body turning steadily through 180 degrees: axis-angle jumps from +pi to -pi there.
    times = np.arange(60) / 30.0
    angles = np.linspace(2.8, 3.5, 60)
    f = RotationFilter(OneEuroConfig(min_cutoff_hz=5.0, beta=1.0))
    for angle, t in zip(angles, times, strict=True):
        wrapped = (angle + math.pi) % (2 * math.pi) - math.pi
        out = f.filter(np.array([[0.0, wrapped, 0.0]]), t)
    truth = axis_angle_to_matrix(torch.tensor([0.0, angles[-1], 0.0], dtype=torch.float64))
    got = axis_angle_to_matrix(torch.as_tensor(out[0]))
    error = math.degrees(math.acos(min(1.0, (float(torch.trace(truth.T @ got)) - 1) / 2)))
    assert error < 3.0


# ---- masks --------------------------------------------------------------------------------------


def test_clean_mask_keeps_the_anchored_component_and_fills_small_holes():
    mask = np.zeros((200, 200), np.uint8)
    mask[40:160, 60:120] = 255  # the person
    mask[100, 90] = 0  # a pinhole
    mask[10:30, 150:190] = 255  # a second blob, not the person
    mask[190, 5] = 255  # a speck
    cleaned = clean_mask(mask, np.array([[90.0, 60.0], [80.0, 150.0]]))
    assert cleaned[100, 90] == 255 and cleaned[50, 70] == 255
    assert not cleaned[10:30, 150:190].any() and cleaned[190, 5] == 0
    both = clean_mask(mask, None)  # without anchors: every big enough part
    assert both[20, 170] == 255 and both[190, 5] == 0
    assert not clean_mask(np.zeros((50, 50), np.uint8), None).any()


def test_background_model_learns_the_scene_and_finds_what_moves():
    rng = np.random.default_rng(2)
    scene = rng.integers(60, 200, size=(120, 160, 3), dtype=np.uint8)
    masker = BackgroundModelMasker("mog2")
    for _ in range(40):
        masker(np.clip(scene + rng.normal(0, 2, scene.shape), 0, 255).astype(np.uint8), None)
    frame = scene.copy()
    frame[30:90, 60:100] = (250, 20, 20)
    mask = masker(frame, None) > 0
    box = np.zeros_like(mask)
    box[30:90, 60:100] = True
    assert (mask & box).sum() / (mask | box).sum() > 0.8
    with pytest.raises(ValueError, match="mog2"):
        BackgroundModelMasker("vibe")


def test_depth_mask_keeps_the_slab_around_the_person():
    depth = np.full((100, 100), 5.0, np.float32)
    depth[20:80, 40:60] = 2.0  # the person at 2 m in front of a wall at 5 m
    depth[0:5, 0:5] = 0.0  # no stereo match
    masker = DepthMasker(slab_m=0.5)
    frame = np.zeros((100, 100, 3), np.uint8)
    assert not masker(frame, None, 2.0).any()  # no depth image yet
    masker.set_depth(depth)
    mask = masker(frame, None, 2.1) > 0
    assert mask[50, 50] and not mask[10, 10] and not mask[2, 2] and mask.sum() == 60 * 20


def test_mask_factory_names_what_is_missing():
    with pytest.raises(ValueError, match="--plate"):
        make_masker("plate")
    with pytest.raises(ValueError, match="unknown mask method"):
        make_masker("magic")


# ---- intrinsics ---------------------------------------------------------------------------------


def test_fov_intrinsics_and_rescaling():
    cam = from_fov(640, 480, 90.0)
    assert cam.K[0, 0] == pytest.approx(320.0) and cam.K[0, 2] == pytest.approx(319.5)
    half = cam.scaled(320, 240)
    assert half.K[0, 0] == pytest.approx(160.0) and half.K[0, 2] == pytest.approx(159.5)
    with pytest.raises(IntrinsicsError, match="--fov"):
        from_fov(640, 480, 0.0)


def test_intrinsics_file_is_checked_and_distortion_undone(tmp_path):
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    dist = np.array([-0.2, 0.05, 0.001, -0.001, 0.0])
    path = tmp_path / "cam.json"
    path.write_text(json.dumps({"K": K.tolist(), "dist": dist.tolist()}))
    cam = load_intrinsics(path, 640, 480)
    rng = np.random.default_rng(3)
    pinhole = rng.uniform([50, 50], [590, 430], size=(40, 2))
    rays = np.concatenate([(pinhole - K[:2, 2]) / 500.0, np.ones((40, 1))], axis=1)
    distorted, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, dist)
    assert np.allclose(cam.undistort_points(distorted.reshape(-1, 2)), pinhole, atol=0.05)
    for bad, message in (
        ({"dist": [0.0] * 5}, '"K"'),
        ({"K": [[1, 0], [0, 1]]}, "3x3"),
        ({"K": K.tolist(), "dist": [0.1, 0.2, 0.3]}, "dist"),
        ({"K": [[500, 0, 2000], [0, 500, 240], [0, 0, 1]]}, "outside"),
    ):
        path.write_text(json.dumps(bad))
        with pytest.raises(IntrinsicsError, match=message):
            load_intrinsics(path, 640, 480)
    path.write_text("{not json")
    with pytest.raises(IntrinsicsError, match="JSON"):
        load_intrinsics(path, 640, 480)
    with pytest.raises(IntrinsicsError, match="does not exist"):
        load_intrinsics(tmp_path / "nope.json", 640, 480)


# ---- frame sources ------------------------------------------------------------------------------


def _write_frames(folder, count=12, size=(64, 48)):
    folder.mkdir(parents=True, exist_ok=True)
    frames = []
    for i in range(count):
        image = np.zeros((size[1], size[0], 3), np.uint8)
        image[:, :, 0] = 20 * i  # red ramps with the frame index
        frames.append(image)
        cv2.imwrite(str(folder / f"frame{i}.png"), image[..., ::-1])
    return frames


def test_image_folder_frames_come_in_natural_order_with_times(tmp_path):
    _write_frames(tmp_path / "imgs")
    (tmp_path / "imgs" / "notes.txt").write_text("not an image")
    source = open_source(tmp_path / "imgs", fps=10.0)
    assert isinstance(source, ImageFolderSource) and len(source) == 12
    frames = list(source)
    assert [f.index for f in frames] == list(range(12))
    assert [int(f.image[0, 0, 0]) for f in frames] == [20 * i for i in range(12)]  # frame10 after frame9
    assert frames[3].timestamp == pytest.approx(0.3)
    cv2.imwrite(str(tmp_path / "imgs" / "frame99.png"), np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(SourceError, match="one camera, one size"):
        list(open_source(tmp_path / "imgs"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(SourceError, match="no images"):
        open_source(tmp_path / "empty")
    with pytest.raises(SourceError, match="neither"):
        open_source(tmp_path / "missing")


def test_video_frames_decode_in_order_with_stream_times(tmp_path):
    frames = _write_frames(tmp_path / "imgs", count=10)
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (64, 48))
    for image in frames:
        writer.write(image[..., ::-1])
    writer.release()
    source = open_source(path)
    assert isinstance(source, VideoSource) and source.fps == pytest.approx(25.0)
    decoded = list(source)
    assert len(decoded) == 10
    assert np.allclose([f.timestamp for f in decoded], np.arange(10) / 25.0, atol=1e-3)
    assert [round(float(f.image[..., 0].mean()) / 20) for f in decoded] == list(range(10))
    broken = tmp_path / "broken.mp4"
    broken.write_bytes(b"\x00" * 100)
    with pytest.raises(SourceError):
        list(open_source(broken))


# ---- network files ------------------------------------------------------------------------------


def test_network_install_reads_only_the_two_files_checks_them_and_is_idempotent(tmp_path, monkeypatch):
    import hashlib

    detector_blob, landmark_blob = b"fake detector network", b"fake landmark network"
    members = {
        "detector": (
            "mediapipe/modules/pose_detection/pose_detection.tflite",
            hashlib.sha256(detector_blob).hexdigest(),
        ),
        "landmarker": (
            "mediapipe/modules/pose_landmark/pose_landmark_full.tflite",
            hashlib.sha256(landmark_blob).hexdigest(),
        ),
    }
    monkeypatch.setattr(model_files, "MODELS", members)
    wheel = tmp_path / "mediapipe-0.10.21-fake.whl"
    with zipfile.ZipFile(wheel, "w") as archive:
        archive.writestr(members["detector"][0], detector_blob)
        archive.writestr(members["landmarker"][0], landmark_blob)
        archive.writestr("mediapipe/evil.py", "raise SystemExit")
    target = tmp_path / "models"
    with pytest.raises(model_files.PoseModelError, match="install_pose_models"):
        model_files.pose_model_paths(target)
    written = model_files.install(target, wheel)
    assert written["detector"].read_bytes() == detector_blob
    assert sorted(p.name for p in target.iterdir()) == [
        "manifest.json",
        "pose_detection.tflite",
        "pose_landmark_full.tflite",
    ]
    stamp = written["detector"].stat().st_mtime_ns
    model_files.install(target, wheel)  # already there: nothing rewritten
    assert written["detector"].stat().st_mtime_ns == stamp
    assert model_files.main(["--dest", str(target), "--status"]) == 0
    written["landmarker"].write_bytes(b"tampered")
    assert not model_files.installed(target)
    with pytest.raises(model_files.PoseModelError, match="checksum"):
        model_files.pose_model_paths(target, verify=True)
    bad = tmp_path / "bad.whl"
    with zipfile.ZipFile(bad, "w") as archive:
        archive.writestr(members["detector"][0], b"other bytes")
        archive.writestr(members["landmarker"][0], landmark_blob)
    with pytest.raises(model_files.PoseModelError, match="checksum mismatch"):
        model_files.install(tmp_path / "other", bad)


def test_camera_frame_parameters_move_to_the_world_frame(body):
    from stg_node.body.params import SmplParams
    from stg_node.tracking.camera import smpl_to_world

    rng = np.random.default_rng(6)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R, t = q * np.sign(np.linalg.det(q)), rng.normal(size=3)
    camera = SmplParams(
        poses=rng.normal(0, 0.2, (24, 3)), Rh=rng.normal(size=3), Th=rng.normal(size=3), betas=np.zeros(10)
    )
    world = smpl_to_world(camera, R, t)

    def joints(p):
        out = body(betas=torch.as_tensor(p.betas), poses=torch.as_tensor(p.poses.reshape(1, 72)),
                   Rh=torch.as_tensor(p.Rh[None]), Th=torch.as_tensor(p.Th[None]))  # fmt: skip
        return out.joints[0].double().numpy()

    assert np.allclose(joints(world) @ R.T + t, joints(camera), atol=1e-4)
    assert np.array_equal(world.poses, camera.poses)
