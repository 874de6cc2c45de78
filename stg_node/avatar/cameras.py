"""Cameras to look at an avatar from: an orbit around the subject, built like the data's cameras.

OpenCV axes (x right, y down, z forward), world-to-camera R, t, as stg_node.data.types.Camera.
The orbit circles the subject about its own up axis (the body's +y carried into the world by
Rh, so it works for z-up ZJU-MoCap worlds and y-up ones alike) at the training camera's
distance and height.
"""

from __future__ import annotations

import math

import numpy as np

from stg_node.data.types import Camera


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, t) of a camera at ``eye`` looking at ``target`` with ``up`` up in the image."""
    forward = target - eye
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-8:  # looking along up: pick any right
        right = np.cross(forward, np.array([1.0, 0.0, 0.0]))
    right = right / np.linalg.norm(right)
    down = np.cross(forward, right)
    R = np.stack([right, down, forward])
    return R, -R @ eye


def body_up(Rh: np.ndarray) -> np.ndarray:
    """The body's up direction (+y in SMPL's frame) in the world, for global rotation ``Rh``."""
    import cv2

    rot, _ = cv2.Rodrigues(np.asarray(Rh, np.float64).reshape(3, 1))
    return rot @ np.array([0.0, 1.0, 0.0])


def orbit(
    center: np.ndarray,
    up: np.ndarray,
    reference: Camera,
    count: int,
    *,
    width: int | None = None,
    height: int | None = None,
) -> list[Camera]:
    """``count`` cameras on a circle about ``up`` through ``center``, starting at ``reference``'s position,
    with its distance, height above the centre and intrinsics."""
    up = up / np.linalg.norm(up)
    eye0 = -reference.R.T @ reference.t
    offset = eye0 - center
    height_off = float(offset @ up)
    radial = offset - height_off * up
    radius = float(np.linalg.norm(radial)) or 3.0
    e1 = radial / np.linalg.norm(radial) if np.linalg.norm(radial) > 1e-6 else _perpendicular(up)
    e2 = np.cross(up, e1)
    w = width or reference.width
    h = height or reference.height
    K = np.array(reference.K, np.float64, copy=True)
    K[0] *= w / reference.width
    K[1] *= h / reference.height
    cams = []
    for i in range(count):
        a = 2.0 * math.pi * i / count
        eye = center + height_off * up + radius * (math.cos(a) * e1 + math.sin(a) * e2)
        R, t = look_at(eye, center, up)
        cams.append(Camera(K=K, R=R, t=t, width=w, height=h, name=f"orbit{i:03d}"))
    return cams


def _perpendicular(v: np.ndarray) -> np.ndarray:
    a = np.array([1.0, 0.0, 0.0]) if abs(v[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    p = np.cross(v, a)
    return p / np.linalg.norm(p)
