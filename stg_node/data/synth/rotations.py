"""Vectorised numpy rotation helpers for the synthetic benchmark (axis-angle, Euler, matrices).

The generator builds poses from anatomical Euler angles and writes SMPL axis-angle vectors;
these helpers do the conversions in float64 so that the written parameters are exact to
float32. They are small on purpose: the body package owns the differentiable torch versions.

Euler convention used throughout the synthetic benchmark: intrinsic Z-Y-X, i.e.
``R = Rz(z) @ Ry(y) @ Rx(x)`` for angles ``(x, y, z)`` (scipy: ``from_euler("ZYX", [z, y, x])``).
"""

from __future__ import annotations

import numpy as np


def axis_rotation(axis: str, angle: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) about a coordinate axis ('x', 'y' or 'z') by ``angle`` radians."""
    angle = np.asarray(angle, dtype=np.float64)
    c, s = np.cos(angle), np.sin(angle)
    one, zero = np.ones_like(angle), np.zeros_like(angle)
    if axis == "x":
        rows = [[one, zero, zero], [zero, c, -s], [zero, s, c]]
    elif axis == "y":
        rows = [[c, zero, s], [zero, one, zero], [-s, zero, c]]
    elif axis == "z":
        rows = [[c, -s, zero], [s, c, zero], [zero, zero, one]]
    else:
        raise ValueError(f"axis must be 'x', 'y' or 'z', got {axis!r}")
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


def euler_zyx_to_matrix(euler: np.ndarray) -> np.ndarray:
    """(..., 3) angles (x, y, z) in radians -> (..., 3, 3) ``Rz(z) @ Ry(y) @ Rx(x)``."""
    euler = np.asarray(euler, dtype=np.float64)
    return (
        axis_rotation("z", euler[..., 2])
        @ axis_rotation("y", euler[..., 1])
        @ axis_rotation("x", euler[..., 0])
    )


def axis_angle_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues: (..., 3) axis-angle -> (..., 3, 3) rotation matrices."""
    rotvec = np.asarray(rotvec, dtype=np.float64)
    angle = np.linalg.norm(rotvec, axis=-1, keepdims=True)
    small = angle < 1e-12
    axis = rotvec / np.where(small, 1.0, angle)
    x, y, z = axis[..., 0], axis[..., 1], axis[..., 2]
    zero = np.zeros_like(x)
    cross = np.stack(
        [np.stack([zero, -z, y], -1), np.stack([z, zero, -x], -1), np.stack([-y, x, zero], -1)], axis=-2
    )
    s = np.sin(angle)[..., None]
    c = np.cos(angle)[..., None]
    eye = np.broadcast_to(np.eye(3), cross.shape)
    return eye + s * cross + (1.0 - c) * (cross @ cross)


def matrix_to_quaternion(matrix: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions (w, x, y, z) with w >= 0.

    Shepperd's method: picks the numerically largest of w, x, y, z as the pivot, so it is
    stable for every rotation including angles near pi.
    """
    m = np.asarray(matrix, dtype=np.float64)
    trace = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    candidates = np.stack([trace, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]], axis=-1)
    pivot = np.argmax(candidates, axis=-1)
    q = np.empty(m.shape[:-2] + (4,))
    # w pivot
    r = np.sqrt(np.maximum(1.0 + trace, 1e-300))
    qw = np.stack(
        [
            0.5 * r,
            (m[..., 2, 1] - m[..., 1, 2]) / (2 * r),
            (m[..., 0, 2] - m[..., 2, 0]) / (2 * r),
            (m[..., 1, 0] - m[..., 0, 1]) / (2 * r),
        ],
        axis=-1,
    )
    # x pivot
    r = np.sqrt(np.maximum(1.0 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2], 1e-300))
    qx = np.stack(
        [
            (m[..., 2, 1] - m[..., 1, 2]) / (2 * r),
            0.5 * r,
            (m[..., 0, 1] + m[..., 1, 0]) / (2 * r),
            (m[..., 0, 2] + m[..., 2, 0]) / (2 * r),
        ],
        axis=-1,
    )
    # y pivot
    r = np.sqrt(np.maximum(1.0 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2], 1e-300))
    qy = np.stack(
        [
            (m[..., 0, 2] - m[..., 2, 0]) / (2 * r),
            (m[..., 0, 1] + m[..., 1, 0]) / (2 * r),
            0.5 * r,
            (m[..., 1, 2] + m[..., 2, 1]) / (2 * r),
        ],
        axis=-1,
    )
    # z pivot
    r = np.sqrt(np.maximum(1.0 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2], 1e-300))
    qz = np.stack(
        [
            (m[..., 1, 0] - m[..., 0, 1]) / (2 * r),
            (m[..., 0, 2] + m[..., 2, 0]) / (2 * r),
            (m[..., 1, 2] + m[..., 2, 1]) / (2 * r),
            0.5 * r,
        ],
        axis=-1,
    )
    for index, value in enumerate((qw, qx, qy, qz)):
        q = np.where((pivot == index)[..., None], value, q)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def matrix_to_axis_angle(matrix: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 3) axis-angle with angle in [0, pi]."""
    q = matrix_to_quaternion(matrix)
    vec = q[..., 1:]
    sin_half = np.linalg.norm(vec, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(sin_half, q[..., :1])
    # angle / sin(angle/2) -> 2 as the angle -> 0
    scale = np.where(sin_half > 1e-12, angle / np.where(sin_half > 1e-12, sin_half, 1.0), 2.0)
    return vec * scale
