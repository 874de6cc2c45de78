"""Default cameras of the renderer when nobody asks for a view: the training camera, and an orbit.

The orbit turns around the axis that is "up" in the training image (the camera's -y axis in
world coordinates), so it works for Y-up (SMPL) and Z-up (ZJU-MoCap) worlds alike. With the
avatar's posed points (:class:`FramedOrbit`) it frames the body as stg-render does: centred,
about two thirds of the image tall, whatever the distance of the training camera. Without them
(an avatar implementation that cannot say where its body is) :func:`orbit_camera` circles the
body's root at the training camera's distance.
"""

from __future__ import annotations

import math

import numpy as np

from stg_node.data.types import Camera


def _rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    x, y, z = axis
    c, s = math.cos(angle), math.sin(angle)
    cross = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    return c * np.eye(3) + s * cross + (1 - c) * np.outer(axis, axis)


def orbit_camera(train: Camera, center: np.ndarray, angle: float) -> Camera:
    """``train`` turned by ``angle`` radians about the up axis through ``center`` (world point)."""
    R = np.asarray(train.R, np.float64)
    t = np.asarray(train.t, np.float64)
    up = -R[1]  # the camera's -y axis, in world coordinates
    turn = _rotation_about(up, angle)
    position = -R.T @ t
    new_position = center + turn @ (position - center)
    new_R = R @ turn.T  # camera axes turned with it: world->camera = R * turn^-1
    new_t = -new_R @ new_position
    return Camera(K=train.K, R=new_R, t=new_t, width=train.width, height=train.height, name="orbit")


def default_camera(width: int = 256, height: int = 256, distance: float = 3.0) -> Camera:
    """A camera on the world z axis looking at the origin, for when no training camera is known."""
    f = 1.2 * max(width, height)
    K = np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    return Camera(
        K=K, R=np.eye(3), t=np.array([0.0, 0.0, distance]), width=width, height=height, name="default"
    )


class FramedOrbit:
    """The default orbit view, framed: turning about the up axis of the training image, aimed at the
    body, about two thirds of the image tall (stg_node.avatar.framing's rule, as stg-render).

    Live bodies move and wave their arms, so the camera is smoothed: the aim point follows the
    body with a time constant of ``smooth_s``; the distance backs off at once when the body needs
    more room (it is never cut) and closes in again over ``release_s``."""

    def __init__(self, fraction: float = 2.0 / 3.0, smooth_s: float = 0.15, release_s: float = 2.0):
        self.fraction = fraction
        self.smooth_s = smooth_s
        self.release_s = release_s
        self.target: np.ndarray | None = None
        self.distance: float | None = None
        self.last: float | None = None

    def camera(self, points: np.ndarray, train: Camera, angle: float, now: float) -> Camera:
        from stg_node.avatar.framing import (
            FramingRule,
            aim,
            camera_at,
            portrait_intrinsics,
            view_rotation,
            viewing_direction,
        )

        R0 = np.asarray(train.R, np.float64)
        up = -R0[1]  # the training image's up, in the world
        eye = -R0.T @ np.asarray(train.t, np.float64).reshape(3)
        forward = viewing_direction(eye, np.asarray(points, np.float64).mean(axis=0), up)
        rotation = view_rotation(_rotation_about(up, angle) @ forward, up)
        K = portrait_intrinsics(train.K, train.height, train.width, train.height)
        target, distance = aim(points, rotation, K, train.width, train.height, FramingRule(self.fraction))
        dt = 0.0 if self.last is None else max(0.0, now - self.last)
        self.last = now
        if self.target is None:
            self.target, self.distance = target, distance
        else:
            follow = 1.0 - math.exp(-dt / self.smooth_s) if self.smooth_s > 0 else 1.0
            self.target = self.target + follow * (target - self.target)
            release = 1.0 - math.exp(-dt / self.release_s) if self.release_s > 0 else 1.0
            smoothed = self.distance + release * (distance - self.distance)
            self.distance = max(distance, smoothed)
        return camera_at(self.target, self.distance, rotation, K, train.width, train.height, "orbit")
