"""Directions of a posed body in its world: which way is up, which way it faces.

A dataset's world is its own (ZJU-MoCap and stg-synth: z up; a tracked video: the camera's
frame, y down), so render cameras take their bearings from the body: SMPL's canonical body has
+y up and faces +z, and ``Rh`` carries both into the world. The cameras themselves are placed
by :mod:`stg_node.avatar.framing`.
"""

from __future__ import annotations

import numpy as np


def _rotation(Rh: np.ndarray) -> np.ndarray:
    import cv2

    rot, _ = cv2.Rodrigues(np.asarray(Rh, np.float64).reshape(3, 1))
    return rot


def body_up(Rh: np.ndarray) -> np.ndarray:
    """The body's up direction (+y in SMPL's frame) in the world, for global rotation ``Rh``."""
    return _rotation(Rh) @ np.array([0.0, 1.0, 0.0])


def body_front(Rh: np.ndarray) -> np.ndarray:
    """The direction the body faces (+z in SMPL's frame) in the world, for global rotation ``Rh``."""
    return _rotation(Rh) @ np.array([0.0, 0.0, 1.0])


def mean_up(Rhs) -> np.ndarray:
    """The unit mean of the bodies' up directions over a sequence (one lean does not tilt a render)."""
    ups = np.stack([body_up(Rh) for Rh in Rhs])
    up = ups.mean(axis=0)
    norm = np.linalg.norm(up)
    return up / norm if norm > 1e-6 else ups[0]
