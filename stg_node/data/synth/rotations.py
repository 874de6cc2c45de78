"""Vectorised numpy rotation helpers for the synthetic benchmark (axis-angle, Euler, matrices).

The generator builds poses from anatomical Euler angles and writes SMPL axis-angle vectors;
these helpers do the conversions in float64 so that the written parameters are exact to
float32. The conversions themselves are the body package's (stg_node.body.lbs), run in
float64 on numpy arrays; only the Euler helpers are the benchmark's own.

Euler convention used throughout the synthetic benchmark: intrinsic Z-Y-X, i.e.
``R = Rz(z) @ Ry(y) @ Rx(x)`` for angles ``(x, y, z)`` (scipy: ``from_euler("ZYX", [z, y, x])``).
"""

from __future__ import annotations

import numpy as np
import torch

from stg_node.body import lbs


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


def _via_body(fn, array: np.ndarray) -> np.ndarray:
    """Run one of stg_node.body's torch rotation conversions in float64 on a numpy array."""
    return fn(torch.from_numpy(np.asarray(array, dtype=np.float64))).numpy()


def axis_angle_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues: (..., 3) axis-angle -> (..., 3, 3) rotation matrices (float64)."""
    return _via_body(lbs.axis_angle_to_matrix, rotvec)


def matrix_to_quaternion(matrix: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions (w, x, y, z) with w >= 0."""
    return _via_body(lbs.matrix_to_quaternion, matrix)


def matrix_to_axis_angle(matrix: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 3) axis-angle with angle in [0, pi]."""
    return _via_body(lbs.matrix_to_axis_angle, matrix)
