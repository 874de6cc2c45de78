"""Anatomical joint limits for SMPL poses, and the map from limited Euler angles to SMPL axis-angle.

Every pose the synthetic benchmark writes is built from per-joint Euler angles
``(x, y, z)`` in the joint's parent-relative SMPL frame (SMPL axes at rest: x = the
subject's left, y = up, z = forward), composed as ``R = Rz(z) @ Ry(y) @ Rx(x)``, and each
angle is clamped to the range below before it becomes an axis-angle vector. Ranges are
those of a healthy adult (rounded from clinical range-of-motion tables, shrunk a little),
so no generated pose hyper-extends a knee or an elbow or twists a neck backwards.

Sign conventions this table encodes (SMPL, left side; the right side mirrors it):
- hips: x < 0 flexes the thigh forward; z > 0 abducts the left leg outwards.
- knees: x > 0 flexes (shank goes backwards), never negative (no hyper-extension).
- spine/neck/head: x > 0 bends forward.
- shoulders: z < 0 lowers the left arm from the T-pose, z > 0 raises it; y < 0 swings it
  forward; x twists it about its own axis.
- elbows: y < 0 flexes the left forearm, never positive (no hyper-extension).

Mirroring across the sagittal plane keeps rotations about x and negates those about y
and z, so a right-side range is the left-side range with its y and z bounds negated.
"""

from __future__ import annotations

import numpy as np

from stg_node.body import SMPL_JOINT_NAMES
from stg_node.data.synth.rotations import euler_zyx_to_matrix, matrix_to_axis_angle

JOINT_NAMES = SMPL_JOINT_NAMES
NUM_JOINTS = len(JOINT_NAMES)
JOINT_INDEX = {name: i for i, name in enumerate(JOINT_NAMES)}

# (x, y, z) ranges in degrees for the midline joints and the LEFT side of paired joints.
_LEFT_AND_MIDLINE_LIMITS_DEG = {
    # The global orientation lives in Rh (ZJU-MoCap's convention): SMPL's own root stays zero.
    "pelvis": ((0, 0), (0, 0), (0, 0)),
    "left_hip": ((-110, 30), (-35, 35), (-25, 45)),
    "spine1": ((-20, 35), (-25, 25), (-20, 20)),
    "left_knee": ((0, 135), (-5, 5), (-5, 5)),
    "spine2": ((-15, 25), (-20, 20), (-15, 15)),
    "left_ankle": ((-25, 40), (-15, 15), (-15, 15)),
    "spine3": ((-15, 20), (-20, 20), (-15, 15)),
    "left_foot": ((-20, 20), (-5, 5), (-5, 5)),
    "neck": ((-30, 40), (-40, 40), (-30, 30)),
    "left_collar": ((-10, 10), (-15, 15), (-15, 25)),
    "head": ((-30, 35), (-45, 45), (-25, 25)),
    "left_shoulder": ((-95, 60), (-85, 40), (-85, 85)),
    "left_elbow": ((-10, 10), (-145, 0), (-5, 5)),
    "left_wrist": ((-40, 40), (-30, 30), (-40, 40)),
    "left_hand": ((-15, 15), (-15, 15), (-15, 15)),
}


def _build_limits() -> np.ndarray:
    limits = np.zeros((NUM_JOINTS, 3, 2))
    for name, ranges in _LEFT_AND_MIDLINE_LIMITS_DEG.items():
        left = np.asarray(ranges, dtype=np.float64)
        limits[JOINT_INDEX[name]] = left
        if name.startswith("left_"):
            right = left.copy()
            right[1:] = -left[1:, ::-1]
            limits[JOINT_INDEX["right_" + name[len("left_") :]]] = right
    return limits


JOINT_LIMITS_DEG = _build_limits()
"""(24, 3, 2) [joint, axis (x, y, z), (low, high)] in degrees, Euler convention of the module doc."""

# Rounding slack when checking a pose read back from float32 axis-angle.
LIMIT_TOLERANCE_DEG = 0.05


def clamp_to_limits(euler_deg: np.ndarray) -> np.ndarray:
    """Clamp (..., 24, 3) Euler angles in degrees to :data:`JOINT_LIMITS_DEG`."""
    euler_deg = np.asarray(euler_deg, dtype=np.float64)
    if euler_deg.shape[-2:] != (NUM_JOINTS, 3):
        raise ValueError(f"euler angles must have shape (..., {NUM_JOINTS}, 3), got {euler_deg.shape}")
    return np.clip(euler_deg, JOINT_LIMITS_DEG[..., 0], JOINT_LIMITS_DEG[..., 1])


def euler_to_smpl_pose(euler_deg: np.ndarray) -> np.ndarray:
    """(..., 24, 3) limited Euler angles in degrees -> (..., 24, 3) SMPL axis-angle (radians).

    The angles are clamped to the joint limits first, so whatever a motion asks for, the
    written pose is anatomically plausible.
    """
    clamped = clamp_to_limits(euler_deg)
    return matrix_to_axis_angle(euler_zyx_to_matrix(np.deg2rad(clamped)))


def within_limits(euler_deg: np.ndarray, tolerance_deg: float = LIMIT_TOLERANCE_DEG) -> np.ndarray:
    """Boolean (..., 24, 3): whether each angle lies in its range (with ``tolerance_deg`` slack)."""
    euler_deg = np.asarray(euler_deg, dtype=np.float64)
    low = JOINT_LIMITS_DEG[..., 0] - tolerance_deg
    high = JOINT_LIMITS_DEG[..., 1] + tolerance_deg
    return (euler_deg >= low) & (euler_deg <= high)
