"""Cameras that frame the avatar: centred, about two thirds of the image tall, never cut.

A render of a trained avatar must show the person whole and large enough, whatever the
distance of the camera it was trained from (a phone held close, a webcam across the room).
The rule, used by ``stg-render`` (orbit and follow cameras) and the renderer node's orbit view:

- look along a given direction (an orbit angle, or the training camera's direction);
- aim at the point that puts the body's projected box in the middle of the image;
- back off until the box is ``fraction`` of the image height tall (default 2/3), or until it
  fits ``1 - 2 margin`` of the image width, whichever is further.

The body is a cloud of points (the posed Gaussian centres); its box is taken between robust
quantiles, so a few stray Gaussians do not shrink the avatar. Everything is a pinhole
projection in closed form, which is what the tests check it against.

Along a sequence (:func:`follow_cameras`) the aim point follows the body, smoothed over
``smooth_s`` seconds, and the distance is the largest any frame needs: the body moves through
the picture at a steady size and is never cut.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from stg_node.data.types import Camera

DEFAULT_FRACTION = 2.0 / 3.0  # of the image height
DEFAULT_MARGIN = 0.04  # of the image width, kept free on each side
DEFAULT_QUANTILE = 0.005  # the body's box: between these quantiles of its points, per image axis
MIN_CLEARANCE_M = 0.05  # the camera stays at least this far in front of every point
MAX_POINTS = 2048  # a frame's points are thinned to at most this many (the box hardly changes)
BISECTIONS = 32  # distance search steps: 2^-32 of the bracket


@dataclass(frozen=True)
class FramingRule:
    fraction: float = DEFAULT_FRACTION
    margin: float = DEFAULT_MARGIN
    quantile: float = DEFAULT_QUANTILE

    def validate(self) -> None:
        if not 0.05 <= self.fraction <= 1.0:
            raise ValueError(f"framing fraction must lie in [0.05, 1], got {self.fraction}")
        if not 0.0 <= self.margin < 0.5:
            raise ValueError(f"framing margin must lie in [0, 0.5), got {self.margin}")
        if not 0.0 <= self.quantile < 0.5:
            raise ValueError(f"framing quantile must lie in [0, 0.5), got {self.quantile}")


def view_rotation(forward: np.ndarray, up: np.ndarray) -> np.ndarray:
    """World-to-camera rotation (rows: right, down, forward; OpenCV axes) looking along ``forward``."""
    forward = np.asarray(forward, np.float64)
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up, np.float64))
    if np.linalg.norm(right) < 1e-8:  # looking along up: any right will do
        right = np.cross(forward, np.array([1.0, 0.0, 0.0]))
        if np.linalg.norm(right) < 1e-8:
            right = np.cross(forward, np.array([0.0, 1.0, 0.0]))
    right = right / np.linalg.norm(right)
    down = np.cross(forward, right)
    return np.stack([right, down, forward])


def thin(points: np.ndarray, limit: int = MAX_POINTS) -> np.ndarray:
    """At most ``limit`` rows of ``points`` (an even stride: deterministic)."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if len(points) <= limit:
        return points
    return points[np.linspace(0, len(points) - 1, limit).round().astype(np.int64)]


def _projected_box(rel: np.ndarray, distance: float, K: np.ndarray, q: float):
    """(u0, u1, v0, v1) pixel box of points ``rel`` (camera axes, relative to the aim point) seen from
    ``distance`` behind the aim point, between the ``q`` and ``1 - q`` quantiles; principal point
    subtracted."""
    depth = distance + rel[:, 2]
    uv = np.stack([K[0, 0] * rel[:, 0] / depth, K[1, 1] * rel[:, 1] / depth])
    if q <= 0 or len(rel) < 3:
        lo, hi = uv.min(axis=1), uv.max(axis=1)
    else:
        lo, hi = np.quantile(uv, [q, 1.0 - q], axis=1)
    return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])


def _distance_for(rel: np.ndarray, K: np.ndarray, half_w: float, half_h: float, q: float) -> float:
    """The smallest distance at which at most a ``q`` share of the points falls outside
    [-half_w, half_w] x [-half_h, half_h] about the principal point, on each side: closed form.

    A point at ``(x, y, z)`` (camera axes, relative to the aim point) with ``y > 0`` stays inside
    the lower edge while ``f y / (d + z) <= half_h``, i.e. for ``d >= f y / half_h - z``; so the
    distance that lets at most ``k`` points out on that side is the ``(k + 1)``-th largest of
    those bounds. The same for the other three sides; the largest of the four wins."""
    n = len(rel)
    near = max(float(-rel[:, 2].min()) + MIN_CLEARANCE_M, MIN_CLEARANCE_M)
    k = int(q * n) if q > 0 else 0
    if k >= n:
        return near
    need = near
    for coord, focal, half in ((rel[:, 0], K[0, 0], half_w), (rel[:, 1], K[1, 1], half_h)):
        for side in (coord, -coord):
            bounds = np.where(side > 0, focal * side / half - rel[:, 2], -np.inf)
            need = max(need, float(np.partition(bounds, n - 1 - k)[n - 1 - k]))
    return need


def aim(
    points: np.ndarray,
    rotation: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    rule: FramingRule | None = None,
) -> tuple[np.ndarray, float]:
    """(aim point, distance): looking with world-to-camera ``rotation``, the points' box is centred on
    the principal point and ``rule.fraction`` of the image tall (or as wide as the image allows)."""
    rule = rule or FramingRule()
    rule.validate()
    points = thin(points)
    if len(points) == 0 or not np.all(np.isfinite(points)):
        raise ValueError("cannot frame the avatar: no finite points")
    K = np.asarray(K, np.float64)
    R = np.asarray(rotation, np.float64)
    target = points.mean(axis=0)
    distance = 1.0
    half_h = 0.5 * rule.fraction * height
    half_w = 0.5 * (1.0 - 2.0 * rule.margin) * width
    for _ in range(8):  # re-centre, re-measure: converges in a few rounds
        rel = (points - target) @ R.T
        distance = _distance_for(rel, K, half_w, half_h, rule.quantile)
        u0, u1, v0, v1 = _projected_box(rel, distance, K, rule.quantile)
        du, dv = 0.5 * (u0 + u1), 0.5 * (v0 + v1)
        if abs(du) < 0.25 and abs(dv) < 0.25:
            break
        # A pixel offset at the depth of the box's middle, back to metres along right/down.
        depth = distance + float(np.median(rel[:, 2]))
        target = target + R[0] * du * depth / K[0, 0] + R[1] * dv * depth / K[1, 1]
    else:  # not settled within the rounds: the distance that keeps the last aim's box inside
        distance = _distance_for((points - target) @ R.T, K, half_w, half_h, rule.quantile)
    return target, distance


def camera_at(
    target: np.ndarray,
    distance: float,
    rotation: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    name: str,
) -> Camera:
    """The camera ``distance`` behind ``target`` along the view direction (rotation's third row)."""
    R = np.asarray(rotation, np.float64)
    eye = np.asarray(target, np.float64) - distance * R[2]
    return Camera(
        K=np.asarray(K, np.float64), R=R, t=-R @ eye, width=int(width), height=int(height), name=name
    )


def frame_points(
    points: np.ndarray,
    forward: np.ndarray,
    up: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    rule: FramingRule | None = None,
    name: str = "framed",
) -> Camera:
    """One camera looking along ``forward`` (``up`` up in the image) that frames ``points`` by the rule."""
    R = view_rotation(forward, up)
    target, distance = aim(points, R, K, width, height, rule)
    return camera_at(target, distance, R, K, width, height, name)


def smooth_track(values: np.ndarray, window: int) -> np.ndarray:
    """Centred moving average over ``window`` rows (shorter at the ends); window <= 1: unchanged."""
    values = np.asarray(values, np.float64)
    if window <= 1 or len(values) < 2:
        return values.copy()
    half = window // 2
    out = np.empty_like(values)
    cumsum = np.concatenate([np.zeros((1,) + values.shape[1:]), np.cumsum(values, axis=0)])
    for i in range(len(values)):
        lo, hi = max(0, i - half), min(len(values), i + half + 1)
        out[i] = (cumsum[hi] - cumsum[lo]) / (hi - lo)
    return out


def follow_cameras(
    frames_points: list[np.ndarray],
    rotations: list[np.ndarray],
    K: np.ndarray,
    width: int,
    height: int,
    rule: FramingRule | None = None,
    *,
    smooth_frames: int = 15,
    name: str = "follow",
) -> list[Camera]:
    """One camera per frame, frame ``i`` looking with ``rotations[i]``: aimed at the body's smoothed
    centre, all at the one distance that keeps every frame's body inside the framed box.

    The box a frame may use is ``rule.fraction`` of the height (the margin of the width); the
    frame that needs it most fills it exactly, the others fill a little less."""
    rule = rule or FramingRule()
    if len(frames_points) != len(rotations) or not frames_points:
        raise ValueError(f"need one rotation per frame, got {len(frames_points)} and {len(rotations)}")
    K = np.asarray(K, np.float64)
    thinned = [thin(p) for p in frames_points]
    targets = np.stack(
        [aim(p, R, K, width, height, rule)[0] for p, R in zip(thinned, rotations, strict=True)]
    )
    targets = smooth_track(targets, smooth_frames)
    half_h = 0.5 * rule.fraction * height
    half_w = 0.5 * (1.0 - 2.0 * rule.margin) * width
    distance = max(
        _distance_for((p - c) @ np.asarray(R).T, K, half_w, half_h, rule.quantile)
        for p, c, R in zip(thinned, targets, rotations, strict=True)
    )
    return [
        camera_at(c, distance, R, K, width, height, f"{name}{i:04d}")
        for i, (c, R) in enumerate(zip(targets, rotations, strict=True))
    ]


def orbit_rotations(forward: np.ndarray, up: np.ndarray, count: int) -> list[np.ndarray]:
    """``count`` view rotations turning once about ``up``, starting looking along ``forward``."""
    up = np.asarray(up, np.float64)
    up = up / np.linalg.norm(up)
    forward = np.asarray(forward, np.float64)
    out = []
    for i in range(count):
        a = 2.0 * math.pi * i / max(count, 1)
        out.append(view_rotation(_rotate(forward, up, a), up))
    return out


def _rotate(v: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues: ``v`` turned by ``angle`` about the unit ``axis``."""
    c, s = math.cos(angle), math.sin(angle)
    return v * c + np.cross(axis, v) * s + axis * (axis @ v) * (1.0 - c)


def viewing_direction(
    eye: np.ndarray, target: np.ndarray, up: np.ndarray, max_elevation_deg: float = 30.0
) -> np.ndarray:
    """The direction from ``eye`` to ``target``, its elevation above/below the plane normal to ``up``
    limited to ``max_elevation_deg`` (a training camera far above or below the person would
    otherwise give an orbit seen from the ceiling)."""
    up = np.asarray(up, np.float64)
    up = up / np.linalg.norm(up)
    d = np.asarray(target, np.float64) - np.asarray(eye, np.float64)
    if np.linalg.norm(d) < 1e-9:
        d = -_any_perpendicular(up)
    vertical = float(d @ up)
    horizontal = d - vertical * up
    if np.linalg.norm(horizontal) < 1e-9:
        horizontal = _any_perpendicular(up)
    horizontal = horizontal / np.linalg.norm(horizontal)
    elevation = math.atan2(vertical, float(np.linalg.norm(d - vertical * up)))
    limit = math.radians(max_elevation_deg)
    elevation = min(max(elevation, -limit), limit)
    return math.cos(elevation) * horizontal + math.sin(elevation) * up


def _any_perpendicular(v: np.ndarray) -> np.ndarray:
    a = np.array([1.0, 0.0, 0.0]) if abs(v[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    p = np.cross(v, a)
    return p / np.linalg.norm(p)


def portrait_intrinsics(
    K: np.ndarray,
    ref_height: int,
    width: int,
    height: int,
    min_fov_deg: float = 20.0,
    max_fov_deg: float = 60.0,
) -> np.ndarray:
    """Intrinsics for ``width x height`` renders from a reference camera's ``K`` (for images
    ``ref_height`` tall): its vertical field of view limited to [min_fov_deg, max_fov_deg] (a very
    wide training lens makes a framed render look distorted, a very long one flat), its pixel
    aspect kept, the principal point centred."""
    K = np.asarray(K, np.float64)
    fy = K[1, 1] * height / ref_height
    fov = math.degrees(2.0 * math.atan(0.5 * height / fy))
    fov = min(max(fov, min_fov_deg), max_fov_deg)
    f = 0.5 * height / math.tan(math.radians(fov) / 2.0)
    aspect = K[0, 0] / K[1, 1]
    return np.array([[f * aspect, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class FramingReport:
    """How renders frame the avatar, from their alpha channels."""

    frames: int
    whole: float  # fraction of frames whose avatar does not touch the image border
    tall_enough: float  # fraction of frames whose avatar is at least `min_height` of the image tall
    both: float  # fraction with both
    median_height: float  # median avatar height / image height
    min_height: float = 0.3

    def as_dict(self) -> dict:
        return {
            "frames": self.frames,
            "whole": self.whole,
            "tall_enough": self.tall_enough,
            "whole_and_tall_enough": self.both,
            "median_height": self.median_height,
            "min_height": self.min_height,
        }


def alpha_extent(alpha: np.ndarray, threshold: int = 32) -> tuple[bool, float]:
    """(touches the border, height fraction) of the avatar in one alpha image (uint8)."""
    a = np.asarray(alpha) >= threshold
    if not a.any():
        return False, 0.0
    rows = np.flatnonzero(a.any(axis=1))
    cols = np.flatnonzero(a.any(axis=0))
    h, w = a.shape
    touches = rows[0] == 0 or cols[0] == 0 or rows[-1] == h - 1 or cols[-1] == w - 1
    return bool(touches), float(rows[-1] - rows[0] + 1) / h


class FramingMeter:
    """Accumulates :func:`alpha_extent` over rendered frames."""

    def __init__(self, min_height: float = 0.3):
        self.min_height = min_height
        self.touches: list[bool] = []
        self.heights: list[float] = []

    def add(self, alpha: np.ndarray) -> None:
        touches, height = alpha_extent(alpha)
        self.touches.append(touches)
        self.heights.append(height)

    def report(self) -> FramingReport:
        n = len(self.heights)
        if n == 0:
            return FramingReport(0, 0.0, 0.0, 0.0, 0.0, self.min_height)
        whole = ~np.asarray(self.touches) & (np.asarray(self.heights) > 0)
        tall = np.asarray(self.heights) >= self.min_height
        return FramingReport(
            frames=n,
            whole=float(whole.mean()),
            tall_enough=float(tall.mean()),
            both=float((whole & tall).mean()),
            median_height=float(np.median(self.heights)),
            min_height=self.min_height,
        )
