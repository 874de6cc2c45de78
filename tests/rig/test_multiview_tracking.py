"""Multi-view tracking: triangulation, the SMPL fit to several calibrated views in the world frame,
the keypoint offsets, the multi-view tracker, the rig pipeline (stg-track CAM1 CAM2 ...
--calibration rig.json) and a rig's videos trained with stg-train --format video --calibration."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from stg_node.body import lbs, load_body_model
from stg_node.calibration.rig import write_rig
from stg_node.cli import track as track_cli
from stg_node.cli import train as train_cli
from stg_node.data.synth.generate import SynthConfig, generate
from stg_node.safe_load import load_npy
from stg_node.tracking.body_points import BodyKeypoints
from stg_node.tracking.evaluation import joints_from_params, mpjpe, pa_mpjpe, write_video
from stg_node.tracking.layouts import get_layout
from stg_node.tracking.multiview import MultiViewTracker
from stg_node.tracking.multiview_fit import MultiViewFitter, triangulate
from stg_node.tracking.poses_file import read_poses
from stg_node.tracking.rig_evaluation import synth_rig
from stg_node.tracking.types import Keypoints
from tests.tracking.trackhelpers import needs_blazepose

CAMERAS = ["1", "3", "5"]  # three of a ring of six, 120 degrees apart


@pytest.fixture(scope="module")
def body():
    return load_body_model()


@pytest.fixture(scope="module")
def subject(tmp_path_factory):
    out = tmp_path_factory.mktemp("rigtrack") / "subject"
    generate(
        SynthConfig(
            out=out,
            seed=5,
            num_frames=24,
            size=256,
            num_novel_views=5,
            view_every=1000,
            train_cameras=(0, 2, 4),
            supersample=1,
        ),  # fmt: skip
        progress=False,
    )
    return out


@pytest.fixture(scope="module")
def recordings(subject, tmp_path_factory):
    """The three cameras as MJPG videos and their rig.json."""
    folder = tmp_path_factory.mktemp("rigvideos")
    videos = [
        write_video(sorted((subject / f"Camera_B{c}").glob("*.png")), folder / f"cam{c}.avi", 30.0)
        for c in CAMERAS
    ]
    rig = synth_rig(subject, CAMERAS)
    return videos, write_rig(folder / "rig.json", rig), rig


def truth(subject, frame):
    p = load_npy(subject / "new_params" / f"{frame}.npy")
    return p["poses"].reshape(24, 3), p["Rh"].reshape(3), p["Th"].reshape(3), p["shapes"].reshape(-1)


def true_joints(body, subject, frames):
    params = [truth(subject, f) for f in frames]
    return joints_from_params(
        body,
        np.stack([p[0].reshape(72) for p in params]),
        np.stack([p[1] for p in params]),
        np.stack([p[2] for p in params]),
        np.stack([p[3] for p in params]),
    )


def projected(body, layout, rig, params, noise_px=0.0, rng=None):
    """Each camera's keypoints at the true body points (the layout's), plus noise."""
    model = BodyKeypoints(body, [t.point for t in layout.targets]).double()
    poses, Rh, Th, betas = params
    with torch.no_grad():
        points = model(torch.as_tensor(betas)[None], torch.as_tensor(poses[1:])[None],
                       torch.as_tensor(Rh)[None], torch.as_tensor(Th)[None])[0].numpy()  # fmt: skip
    views = []
    for camera in rig.cameras:
        uv = (points @ camera.R.T + camera.t) @ camera.K.T
        uv = uv[:, :2] / uv[:, 2:]
        xy, score = np.zeros((layout.num_points, 2)), np.zeros(layout.num_points)
        for k, target in enumerate(layout.targets):
            for source in target.sources:
                xy[source], score[source] = uv[k], 1.0
        if noise_px:
            xy = xy + rng.normal(0.0, noise_px, xy.shape)
        views.append(Keypoints(layout=layout.name, xy=xy.astype(np.float32), score=score.astype(np.float32)))
    return views


def test_triangulation_recovers_points_and_outvotes_a_wrong_view():
    rng = np.random.default_rng(0)
    points = rng.uniform(-0.5, 0.5, (10, 3)) + [0, 0, 0.0]
    cams = []
    for angle in (0.0, 1.2, 2.4, 3.6):
        R = cv_rotation([0.0, angle, 0.0])
        t = -R @ np.array([3 * np.sin(angle), 0.0, -3 * np.cos(angle)])
        cams.append(np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]) @ np.column_stack([R, t]))
    P = np.stack(cams)
    h = np.c_[points, np.ones(10)]
    xy = np.einsum("vij,kj->vki", P, h)
    xy = xy[..., :2] / xy[..., 2:]
    found = triangulate(P, xy, np.ones((4, 10)))
    np.testing.assert_allclose(found.points, points, atol=1e-6)
    assert np.all(found.views == 4)
    wrong = xy.copy()
    wrong[2, 3] += [60.0, -40.0]  # one view put point 3 somewhere else
    found = triangulate(P, wrong, np.ones((4, 10)))
    np.testing.assert_allclose(found.points[3], points[3], atol=1e-6)
    assert found.views[3] == 3 and found.views[0] == 4
    weak = np.ones((4, 10))
    weak[1:, 5] = 0.0  # point 5 seen by one camera only
    assert np.isnan(triangulate(P, xy, weak).points[5]).all()


def cv_rotation(vector):
    import cv2

    return cv2.Rodrigues(np.asarray(vector, dtype=np.float64))[0]


def test_the_multiview_fit_recovers_the_body_in_the_world_frame(body, subject):
    rig = synth_rig(subject, CAMERAS)
    layout = get_layout("smpl24")
    fitter = MultiViewFitter(body, layout, [(c.K, c.R, c.t) for c in rig.cameras])
    rng = np.random.default_rng(0)
    results = []
    for i in range(12):
        views = projected(body, layout, rig, truth(subject, i), noise_px=1.0, rng=rng)
        result = fitter.fit_views(views, [v.xy.astype(np.float64) for v in views], i / 30)
        fitter.add_calibration(result, 1.0)
        results.append(result)
    stack = {k: np.stack([getattr(r, k) for r in results]) for k in ("Rh", "Th", "betas")}
    pred = joints_from_params(
        body, np.stack([r.poses.reshape(72) for r in results]), stack["Rh"], stack["Th"], stack["betas"]
    )
    gt = true_joints(body, subject, range(12))
    assert mpjpe(pred, gt).mean() < 0.012 and pa_mpjpe(pred, gt).mean() < 0.010
    # World frame, absolute: the pelvis where it is, without any alignment.
    assert np.linalg.norm(pred[:, 0] - gt[:, 0], axis=1).mean() < 0.012
    assert np.median([r.rms_px for r in results]) < 2.5


def test_keypoint_offsets_move_a_point_with_its_carrier_bone(body):
    layout = get_layout("smpl24")
    points = [t.point for t in layout.targets]
    plain = BodyKeypoints(body, points).double()
    offset = np.array([0.01, 0.02, -0.03])
    moved = BodyKeypoints(
        body, points, {"left_elbow": (16, tuple(offset))}
    ).double()  # carried by left_shoulder
    pose = torch.zeros(1, 23, 3, dtype=torch.float64)
    pose[0, 15] = torch.tensor([0.0, 0.0, -1.0])  # the left shoulder lowers the arm
    zero, betas = torch.zeros(1, 3, dtype=torch.float64), torch.zeros(1, 10, dtype=torch.float64)
    a, b = plain(betas, pose, zero, zero)[0].numpy(), moved(betas, pose, zero, zero)[0].numpy()
    elbow = layout.names.index("left_elbow")
    rotation = lbs.axis_angle_to_matrix(torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)).numpy()
    np.testing.assert_allclose(b[elbow] - a[elbow], rotation @ offset, atol=1e-9)
    np.testing.assert_allclose(np.delete(b, elbow, 0), np.delete(a, elbow, 0), atol=1e-12)


class TrueDetector:
    """A detector that reports the true keypoints of its camera (or nothing on chosen frames)."""

    layout = "smpl24"

    def __init__(self, body, rig, view, subject, blind=()):
        self.body, self.rig, self.view, self.subject, self.blind = body, rig, view, subject, set(blind)
        self.frame = 0

    def reset(self):
        pass

    def __call__(self, image):
        frame = self.frame
        self.frame += 1
        if frame in self.blind:
            return None
        layout = get_layout("smpl24")
        return projected(self.body, layout, self.rig, truth(self.subject, frame))[self.view]


def test_the_multiview_tracker_reports_single_views_and_nobody(body, subject):
    from stg_node.data.io import read_image
    from stg_node.tracking.masks import NoMasker

    rig = synth_rig(subject, CAMERAS)
    detectors = [TrueDetector(body, rig, v, subject, blind={3, 4} if v else {4}) for v in range(3)]
    tracker = MultiViewTracker(detectors, body, rig, maskers=[NoMasker() for _ in range(3)])
    results = []
    for i in range(6):
        frames = [read_image(subject / f"Camera_B{c}" / f"{i:06d}.png") for c in CAMERAS]
        results.append(tracker.estimate(frames, i / 30))
    assert all(r.views_used == 3 and r.confidence > 0.5 for r in results[:3])
    assert results[3].views_used == 1 and "single_view" in results[3].flags
    assert results[4].confidence == 0.0 and results[4].flags == ("no_person",)
    np.testing.assert_array_equal(results[4].smpl.Th, results[3].smpl.Th)  # the last pose is held
    assert [m.shape for m in results[0].masks] == [(256, 256)] * 3
    with pytest.raises(ValueError, match="expected 3 frames"):
        tracker.estimate(frames[:2], 1.0)


@needs_blazepose
def test_stg_track_with_a_rig_tracks_in_the_world_frame(body, subject, recordings, tmp_path, capsys):
    videos, rig_path, rig = recordings
    out = tmp_path / "POSES.npz"
    code = track_cli.main([*map(str, videos), "--calibration", str(rig_path), "--out", str(out),
                           "--masks", str(tmp_path / "masks"), "--no-progress"])  # fmt: skip
    assert code == 0, capsys.readouterr().err
    tracked = read_poses(out)
    assert tracked.cameras == ("1", "3", "5") and tracked.camera_frames.shape == (24, 3)
    np.testing.assert_array_equal(tracked.camera_frames[:, 0], np.arange(24))
    assert (tmp_path / "masks" / "5" / "000023.png").is_file()
    gt = true_joints(body, subject, range(24))
    pred = joints_from_params(body, tracked.poses, tracked.Rh, tracked.Th, tracked.shapes)
    confident = tracked.confidence >= 0.5
    assert confident.mean() > 0.7
    # Reduced size (256 px, 3 cameras, 24 frames): generous bounds; the full figure is
    # tools/eval_track.py --rig 4 (docs/BENCHMARKS.md).
    assert mpjpe(pred[confident], gt[confident]).mean() < 0.06
    assert np.linalg.norm(pred[confident, 0] - gt[confident, 0], axis=1).mean() < 0.06  # where, not just how
    # --cameras names the inputs' cameras when they come in another order
    reordered = tmp_path / "reordered.npz"
    assert track_cli.main([str(videos[2]), str(videos[0]), str(videos[1]), "--calibration", str(rig_path),
                           "--cameras", "5,1,3", "--out", str(reordered), "--no-progress"]) == 0  # fmt: skip
    assert read_poses(reordered).cameras == ("5", "1", "3")


def test_stg_track_rig_usage_and_unsynchronised_inputs(recordings, tmp_path, capsys):
    videos, rig_path, _ = recordings
    out = str(tmp_path / "p.npz")
    assert track_cli.main([str(videos[0]), str(videos[1]), "--out", out]) == 2
    assert "need --calibration" in capsys.readouterr().err
    assert track_cli.main([*map(str, videos[:2]), "--calibration", str(rig_path), "--out", out]) == 1
    assert "2 inputs for a rig of 3 cameras" in capsys.readouterr().err
    # A camera whose capture times say it lost a third of a second: refused, saying where and how much.
    stamps = [i / 30 for i in range(24)]
    stamps = stamps[:10] + [s + 0.3 for s in stamps[10:]]
    videos[2].with_name(videos[2].stem + ".timestamps.txt").write_text(
        "\n".join(f"{1000 * s:.1f}" for s in stamps)
    )
    try:
        assert (
            track_cli.main([*map(str, videos), "--calibration", str(rig_path), "--out", out, "--no-progress"])
            == 1
        )
        assert "is not synchronised with" in capsys.readouterr().err
    finally:
        videos[2].with_name(videos[2].stem + ".timestamps.txt").unlink()


@needs_blazepose
def test_a_rigs_videos_train_with_every_camera(recordings, tmp_path, capsys):
    videos, rig_path, _ = recordings
    data = tmp_path / "recordings"
    data.mkdir()
    for video, name in zip(videos, CAMERAS, strict=True):
        (data / f"{name}.avi").symlink_to(video)
    out = tmp_path / "run"
    args = ["--data", str(data), "--format", "video", "--calibration", str(rig_path), "--out", str(out)]
    code = train_cli.main([*args, "--preset", "fast", "--iters", "4", "--size", "128", "--no-progress"])
    assert code == 0, capsys.readouterr().err
    config = json.loads((out / "config.json").read_text())
    assert config["data"]["train_cameras"] == CAMERAS
    cameras = json.loads((out / "video_data" / "cameras.json").read_text())["cameras"]
    assert list(cameras) == CAMERAS
    np.testing.assert_allclose(cameras["3"]["R"], synth_rig_R(recordings, "3"))
    summary = json.loads((out / "summary.json").read_text())
    assert (
        summary["frames"] % 3 == 0 and summary["frames"] >= 3 * 12
    )  # every camera of the confident instants
    assert train_cli.main(["--data", str(data), "--format", "zju", "--calibration", str(rig_path), "--out",
                           str(tmp_path / "x")]) == 2  # fmt: skip


def synth_rig_R(recordings, name):
    return recordings[2][name].R


@needs_blazepose
def test_the_nodes_rig_estimator_tracks_bus_frames_in_the_world(body, subject, recordings):
    from stg_node.bus import Frame
    from stg_node.data.io import read_image
    from stg_node.nodes.rig import RigTrackingEstimator

    _, _, rig = recordings
    estimator = RigTrackingEstimator(max_side=256)
    gt = true_joints(body, subject, range(4))
    for i in range(4):
        frames = []
        for camera in rig.cameras:
            frame = Frame(index=i, time=i / 30, camera_id=camera.name,
                          image=read_image(subject / f"Camera_B{camera.name}" / f"{i:06d}.png"),
                          K=camera.K, R=camera.R, t=camera.t)  # fmt: skip
            frame.header.stamp_ns = int((100 + i / 30) * 1e9)
            frames.append(frame)
        result = estimator.estimate_set(frames)
        assert result.confidence > 0.4 and len(result.masks) == 3
        pelvis = joints_from_params(body, result.smpl.poses.reshape(1, 72), result.smpl.Rh[None],
                                    result.smpl.Th[None], result.smpl.betas[None])[0, 0]  # fmt: skip
        assert np.linalg.norm(pelvis - gt[i, 0]) < 0.1  # the rig's world frame, not a camera's
    tracker = estimator.tracker
    estimator.estimate_set(frames)  # the same cameras: the same tracker
    assert estimator.tracker is tracker
    with pytest.raises(ValueError, match="not available for a rig"):
        RigTrackingEstimator(mask="plate", plate="x.png")
