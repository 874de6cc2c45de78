"""Framing cameras (stg_node.avatar.framing) against closed-form pinhole projection.

The projection used to check is OpenCV's (cv2.projectPoints), not the module's own, and the
point sets are boxes whose extreme corners are known: the framed box must come out centred and
exactly the asked fraction of the image tall (or as wide as the margin allows).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from stg_node.avatar.framing import (
    FramingMeter,
    FramingRule,
    alpha_extent,
    follow_cameras,
    frame_points,
    orbit_rotations,
    portrait_intrinsics,
    viewing_direction,
)

EXACT = FramingRule(quantile=0.0)  # the true extremes, so the closed form is exact


def box_points(center, size, n=9):
    """A filled axis-aligned box's grid of points (its corners included)."""
    axes = [np.linspace(c - s / 2, c + s / 2, n) for c, s in zip(center, size, strict=True)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def project(camera, points):
    rvec, _ = cv2.Rodrigues(np.asarray(camera.R, np.float64))
    uv, _ = cv2.projectPoints(points, rvec, np.asarray(camera.t, np.float64), camera.K, None)
    return uv.reshape(-1, 2)


def intrinsics(f, w, h):
    return np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("f", [200.0, 600.0, 2000.0])
@pytest.mark.parametrize("center", [(0.0, 0.0, 0.9), (4.0, -7.0, 2.5)])
def test_a_standing_body_is_centred_and_two_thirds_of_the_height(f, center):
    w, h = 320, 240
    points = box_points(center, (0.5, 0.3, 1.8))  # a person-sized box, z up
    K = intrinsics(f, w, h)
    camera = frame_points(
        points, forward=(0.0, 1.0, 0.0), up=(0.0, 0.0, 1.0), K=K, width=w, height=h, rule=EXACT
    )
    uv = project(camera, points)
    height = uv[:, 1].max() - uv[:, 1].min()
    assert height == pytest.approx(2 / 3 * h, rel=2e-3)
    centre = 0.5 * (uv.min(axis=0) + uv.max(axis=0))
    np.testing.assert_allclose(centre, [(w - 1) / 2, (h - 1) / 2], atol=0.5)
    # It looks along the asked direction with the body upright in the image.
    np.testing.assert_allclose(camera.R[2], [0.0, 1.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(camera.R[1], [0.0, 0.0, -1.0], atol=1e-9)


def test_a_wide_body_is_limited_by_the_width():
    w, h = 200, 400
    rule = FramingRule(quantile=0.0, margin=0.05)
    points = box_points((0.0, 0.0, 1.0), (3.0, 0.3, 1.8))  # arms spread far, a tall narrow image
    camera = frame_points(points, (0.0, 1.0, 0.0), (0.0, 0.0, 1.0), intrinsics(300.0, w, h), w, h, rule)
    uv = project(camera, points)
    assert uv[:, 0].max() - uv[:, 0].min() == pytest.approx(0.9 * w, rel=2e-3)
    assert uv[:, 1].max() - uv[:, 1].min() < 2 / 3 * h
    assert uv[:, 0].min() > 0 and uv[:, 0].max() < w - 1


def test_stray_points_do_not_shrink_the_avatar():
    w = h = 256
    body = box_points((0.0, 0.0, 0.9), (0.5, 0.3, 1.8), n=15)
    strays = np.array([[0.0, 0.0, 6.0], [3.0, 0.0, 0.0]])  # two floaters far away
    camera = frame_points(np.concatenate([body, strays]), (0, 1, 0), (0, 0, 1), intrinsics(300.0, w, h), w, h)
    uv = project(camera, body)
    assert uv[:, 1].max() - uv[:, 1].min() > 0.6 * h


def test_a_walking_body_is_followed_whole_at_one_size():
    w = h = 256
    K = intrinsics(350.0, w, h)
    # Walks 3 m across and 2 m towards the camera, raising an arm half-way.
    frames = []
    for i in range(40):
        s = i / 39
        body = box_points((3.0 * s - 1.5, -2.0 * s, 0.9), (0.5, 0.3, 1.8), n=5)
        if 15 <= i < 25:
            body = np.concatenate([body, [[3.0 * s - 1.5 + 0.9, -2.0 * s, 1.6]]])
        frames.append(body)
    rotations = orbit_rotations((0.0, 1.0, 0.0), (0.0, 0.0, 1.0), 1) * len(frames)
    cameras = follow_cameras(frames, rotations, K, w, h, EXACT, smooth_frames=9)
    heights = []
    for camera, body in zip(cameras, frames, strict=True):
        uv = project(camera, body)
        assert uv.min() >= 0 and uv[:, 0].max() <= w - 1 and uv[:, 1].max() <= h - 1  # never cut
        heights.append((uv[:, 1].max() - uv[:, 1].min()) / h)
    # The frame that needs the most room fills the framed box; none is smaller than 55 %.
    assert max(heights) <= 2 / 3 + 1e-3
    assert min(heights) > 0.55
    eyes = np.stack([-c.R.T @ c.t for c in cameras])
    assert np.ptp(eyes[:, 0]) > 2.0  # the camera travels with the body


def test_an_orbit_turns_once_about_up_and_keeps_the_elevation():
    forward = viewing_direction(eye=(0.0, -3.5, 1.3), target=(0.0, 0.0, 0.9), up=(0.0, 0.0, 1.0))
    rotations = orbit_rotations(forward, (0.0, 0.0, 1.0), 8)
    elevations = [math.degrees(math.asin(-R[2][2])) for R in rotations]  # forward's z, looking down
    np.testing.assert_allclose(elevations, math.degrees(math.atan2(0.4, 3.5)), atol=1e-6)
    azimuths = np.degrees(np.unwrap([math.atan2(R[2][1], R[2][0]) for R in rotations]))
    np.testing.assert_allclose(np.diff(azimuths) % 360, 45.0, atol=1e-6)


def test_a_camera_far_above_gives_a_limited_elevation():
    forward = viewing_direction(eye=(0.0, -1.0, 10.0), target=(0.0, 0.0, 1.0), up=(0.0, 0.0, 1.0))
    assert math.degrees(math.asin(-forward[2])) == pytest.approx(30.0)


def test_portrait_intrinsics_limit_the_field_of_view():
    wide = portrait_intrinsics(intrinsics(100.0, 640, 480), 480, 256, 256)  # ~135 degrees tall
    assert math.degrees(2 * math.atan(128 / wide[1, 1])) == pytest.approx(60.0)
    normal = portrait_intrinsics(intrinsics(800.0, 640, 480), 480, 240, 240)  # 33 degrees: kept
    assert normal[1, 1] == pytest.approx(400.0)
    assert normal[0, 2] == normal[1, 2] == pytest.approx(119.5)


def test_the_meter_reads_cut_and_small_avatars_from_alpha():
    alpha = np.zeros((100, 100), np.uint8)
    alpha[20:80, 40:60] = 255  # whole, 60 % tall
    assert alpha_extent(alpha) == (False, pytest.approx(0.6))
    cut = np.zeros_like(alpha)
    cut[0:50, 40:60] = 255  # touches the top border
    small = np.zeros_like(alpha)
    small[40:60, 40:60] = 255  # 20 % tall
    meter = FramingMeter(min_height=0.3)
    for a in (alpha, cut, small, alpha):
        meter.add(a)
    report = meter.report()
    assert report.frames == 4
    assert report.whole == pytest.approx(0.75)
    assert report.tall_enough == pytest.approx(0.75)
    assert report.both == pytest.approx(0.5)
