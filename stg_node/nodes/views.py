"""Default cameras of the renderer when nobody asks for a view: the training camera, and an orbit.

The orbit circles the body at the training camera's distance and height, around the axis that
is "up" in the training image (the camera's -y axis in world coordinates), so it works for
Y-up (SMPL) and Z-up (ZJU-MoCap) worlds alike.
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
