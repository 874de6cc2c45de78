"""stg-calibrate against synthetic board captures with known truth (stg_node.calibration.synthetic).

The truth never passes through the calibration code: the images are rendered from the board's
printable image by the exact homography of each pose and warped through OpenCV's lens model,
and the answer is compared with the cameras that rendered them (expressed in the first
camera's frame, the calibration's default world).
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from stg_node.calibration.board import BoardDetector, BoardSpec
from stg_node.calibration.rig import RigError, read_rig, write_rig
from stg_node.calibration.solve import CalibrationError, calibrate_rig, project
from stg_node.calibration.synthetic import rig_errors, ring_rig, synthetic_capture
from stg_node.cli import calibrate as cli

SPEC = BoardSpec(9, 6, 0.07, 0.052)  # 63 x 42 cm: an A2 print


errors_against_truth = rig_errors


@pytest.fixture(scope="module")
def capture():
    """Reduced size: three cameras over 150 degrees, 2 m from the middle, 480x360; 20 close-ups for
    each lens, then 40 instants of the board moving in the middle (about 15 s to render)."""
    rig = ring_rig(3, size=(480, 360), radius=2.0, seed=1, arc_deg=150)
    return synthetic_capture(rig, SPEC, 40, seed=11, close_ups=20)


@pytest.fixture(scope="module")
def detections(capture):
    detector = BoardDetector(SPEC)
    return [[detector(image) for image in views] for views in capture.images]


def test_projection_matches_opencv():
    rng = np.random.default_rng(0)
    points = rng.uniform(-0.5, 0.5, (50, 3)) + [0, 0, 2.0]
    K = np.array([[500.0, 0, 320.5], [0, 490.0, 240.2], [0, 0, 1]])
    dist = np.array([-0.2, 0.05, 0.001, -0.002, 0.01])
    rvec, tvec = np.array([0.1, -0.2, 0.05]), np.array([0.02, -0.1, 0.3])
    ours = project(points, rvec, tvec, K, dist)
    theirs, _ = cv2.projectPoints(points, rvec, tvec, K, dist)
    np.testing.assert_allclose(ours, theirs.reshape(-1, 2), atol=1e-9)


def test_board_corners_are_found_where_the_printed_image_puts_them():
    ppm = 2000.0
    image = SPEC.image(ppm)
    found = BoardDetector(SPEC)(image)
    assert found is not None and len(found) == SPEC.num_corners == 40
    # pixel (r, c) of the print is board point ((c + 0.5) / ppm, (r + 0.5) / ppm)
    expected = found.object_points[:, :2] * ppm - 0.5
    np.testing.assert_allclose(found.image_points, expected, atol=0.1)


def test_detected_corners_agree_with_the_rendered_truth(capture, detections):
    errors = []
    for (R, t), row in zip(capture.poses, detections, strict=True):
        for camera, found in zip(capture.rig.cameras, row, strict=True):
            if found is None:
                continue
            truth = project(
                found.object_points,
                cv2.Rodrigues(camera.R @ R)[0],
                camera.R @ t + camera.t,
                camera.K,
                camera.dist,
            )
            errors.append(np.linalg.norm(truth - found.image_points, axis=1))
    errors = np.concatenate(errors)
    assert np.median(errors) < 0.2, np.median(errors)


def test_a_rig_calibrates_to_its_truth(capture, detections):
    rig = capture.rig
    result = calibrate_rig(rig.names, [c.image_size for c in rig.cameras], detections, SPEC)
    for report in result.reports:
        assert report.rms_px <= 0.5, report
        assert report.views >= 20
    for name, (centre_m, rotation_deg) in zip(rig.names, errors_against_truth(result.rig, rig), strict=True):
        assert centre_m <= 0.01, (name, centre_m)
        assert rotation_deg <= 0.5, (name, rotation_deg)
    for est, tru in zip(result.rig.cameras, rig.cameras, strict=True):
        assert abs(est.K[0, 0] - tru.K[0, 0]) / tru.K[0, 0] < 0.005
        assert abs(est.K[0, 2] - tru.K[0, 2]) < 3.0
        # The lens: the same distortion at the image corner, within a pixel.
        corner = np.array([[0.0, 0.0]])
        ideal_est = cv2.undistortPoints(corner, est.K, est.dist, P=est.K)
        ideal_tru = cv2.undistortPoints(corner, tru.K, tru.dist, P=tru.K)
        assert np.linalg.norm(ideal_est - ideal_tru) < 1.0


def test_board_origin_puts_the_world_on_the_first_board(capture, detections):
    rig = capture.rig
    result = calibrate_rig(rig.names, [c.image_size for c in rig.cameras], detections, SPEC, origin="board")
    # The first instant any camera saw: in the new world that board lies in z = 0 with its
    # corner at the origin, x along its columns.
    first = next(i for i, row in enumerate(detections) if any(d is not None for d in row))
    R_b, t_b = capture.poses[first]
    corners_world_truth = SPEC.corners() @ R_b.T + t_b
    camera = next(c for c, d in zip(result.rig.cameras, detections[first], strict=True) if d is not None)
    truth_camera = rig[camera.name]
    in_camera = corners_world_truth @ truth_camera.R.T + truth_camera.t
    in_new_world = (in_camera - camera.t) @ camera.R
    expected = SPEC.corners() @ np.diag([1.0, -1.0, -1.0])
    np.testing.assert_allclose(in_new_world, expected, atol=0.01)


def test_a_camera_that_never_shares_a_sighting_is_named(capture, detections):
    rig = capture.rig
    alone = [list(row) for row in detections]
    for row in alone:  # camera 3 sees the board only when nobody else does
        if row[2] is not None and (row[0] is not None or row[1] is not None):
            row[2] = None
    with pytest.raises(CalibrationError, match="cam3"):
        calibrate_rig(rig.names, [c.image_size for c in rig.cameras], alone, SPEC)
    none_at_all = [[d if v != 1 else None for v, d in enumerate(row)] for row in detections]
    with pytest.raises(CalibrationError, match="'cam2' saw the board at 0 instant"):
        calibrate_rig(rig.names, [c.image_size for c in rig.cameras], none_at_all, SPEC)


def test_rig_file_round_trip_and_errors(tmp_path, capture):
    path = write_rig(tmp_path / "rig.json", capture.rig)
    back = read_rig(path)
    assert back.names == capture.rig.names
    for a, b in zip(back.cameras, capture.rig.cameras, strict=True):
        np.testing.assert_allclose(a.K, b.K)
        np.testing.assert_allclose(a.R, b.R)
        assert a.image_size == b.image_size
    doc = json.loads(path.read_text())
    assert set(doc["cameras"]["cam1"]) == {"K", "dist", "R", "t", "image_size"}
    doc["cameras"]["cam2"]["R"] = np.diag([1.0, 1.0, 2.0]).tolist()
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    with pytest.raises(RigError, match="cam2.*not a rotation"):
        read_rig(tmp_path / "bad.json")
    del doc["cameras"]["cam1"]["image_size"]
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    with pytest.raises(RigError, match="cam1.*image_size"):
        read_rig(tmp_path / "bad.json")
    with pytest.raises(RigError, match="does not exist"):
        read_rig(tmp_path / "missing.json")


def test_stg_calibrate_on_image_folders(tmp_path, capture, capsys):
    folders = capture.write(tmp_path / "capture")
    out = tmp_path / "rig.json"
    code = cli.main(
        [
            *map(str, folders),
            "--out",
            str(out),
            "--board",
            "9x6",
            "--square",
            "0.07",
            "--marker",
            "0.052",
            "--no-progress",
        ]
    )
    assert code == 0
    printed = capsys.readouterr().out
    assert "RMS px" in printed and "cam3" in printed
    rig = read_rig(out)
    assert rig.names == ["cam1", "cam2", "cam3"]
    assert rig.calibration["board"]["columns"] == 9
    assert all(r["rms_px"] <= 0.5 for r in rig.calibration["cameras"].values())
    assert max(c for c, _ in errors_against_truth(rig, capture.rig)) <= 0.01


def test_stg_calibrate_usage_errors(tmp_path, capsys):
    assert cli.main(["a", "--out", str(tmp_path / "r.json"), "--square", "0.08"]) == 2
    assert "--square and --marker" in capsys.readouterr().err
    assert cli.main([str(tmp_path), "--out", "r.json", "--square", "0.08", "--marker", "0.1"]) == 2
    assert "marker size < square size" in capsys.readouterr().err
    assert (
        cli.main(["x", "y", "--cameras", "a,a", "--out", "r.json", "--square", ".08", "--marker", ".06"]) == 2
    )


def test_write_board_prints_a_detectable_board(tmp_path):
    out = tmp_path / "board.png"
    assert (
        cli.main(["--write-board", str(out), "--board", "6x4", "--square", "0.05", "--marker", "0.035"]) == 0
    )
    image = cv2.imread(str(out), cv2.IMREAD_GRAYSCALE)
    found = BoardDetector(BoardSpec(6, 4, 0.05, 0.035))(image)
    assert found is not None and len(found) == 15


@pytest.mark.slow
def test_a_four_camera_rig_at_full_size_meets_the_targets():
    """The issue's targets on a 640x480 four-camera ring 2.5 m around the middle, several seeds:
    reprojection <= 0.5 px, camera centres within 1 cm, rotations within 0.5 degrees."""
    detector = BoardDetector(SPEC)
    for seed in (1, 2, 3):
        rig = ring_rig(4, seed=seed)
        capture = synthetic_capture(rig, SPEC, 80, seed=seed + 10, close_ups=30)
        detections = [[detector(image) for image in views] for views in capture.images]
        result = calibrate_rig(rig.names, [c.image_size for c in rig.cameras], detections, SPEC)
        assert max(r.rms_px for r in result.reports) <= 0.5
        for centre_m, rotation_deg in errors_against_truth(result.rig, rig):
            assert centre_m <= 0.01 and rotation_deg <= 0.5, (seed, centre_m, rotation_deg)
