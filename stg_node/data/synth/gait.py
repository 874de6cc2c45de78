"""Planted feet for the synthetic walks: the body travels by what its stance foot allows.

The motion generator (motions.py) drives a walking gait's joint angles and the body's travel
separately (a speed along the facing direction); on its own the stance foot slides over the floor
(over 0.1 s the stance foot of the ``approach`` subject moved 1.7 times as far as the pelvis). A
real walker's stance foot stays where it was put while the body passes over it, so the body's
travel between two frames is fixed by the legs' geometry. A focal-length estimate from footage
leans on exactly that (stg_node.tracking.focal: a wrong focal length scales the travel in depth
and not the legs), so the benchmark's walks must have it.

Given the posed skeleton of every frame (the body model's joints, so it holds for any body shape)
:class:`Feet` gives each step ``i -> i + 1`` of a walking frame its ground-plane travel: the stance
leg is the one whose ankle is lower over the two frames, and the body moves so that this ankle
keeps its place on the floor plane, whatever the body turns meanwhile (the ankle offsets are
turned by the frames' yaw). Stride and speed are then what the gait's joint angles give, for any
gait; heading, turning and the walking circle's steering stay the motion's. Frames that do not
walk keep the motion's own travel; where walking cross-fades with standing (or the ``approach``
subject turns round stepping on the spot) the two steps are blended by the walking weight, and the
foot slides or pivots there. The ankle is pinned in the floor plane only: the generator then lifts
each frame so its lowest vertex touches the floor, so the planted ankle's height follows the
foot's roll (heel, sole, toes) by a few centimetres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stg_node.data.synth.joint_limits import JOINT_INDEX

ANKLES = (JOINT_INDEX["left_ankle"], JOINT_INDEX["right_ankle"])
UP_AXIS = 2  # the world's z (motions.py: z up, floor at z = 0)


def stance_legs(joints: np.ndarray) -> np.ndarray:
    """(N - 1,) index into ``ANKLES`` of the stance leg of each step ``i -> i + 1``: the leg whose
    ankle is lower, summed over the step's two frames (``joints`` (N, 24, 3), z up)."""
    heights = np.asarray(joints)[:, list(ANKLES), UP_AXIS]  # (N, 2)
    return np.argmin(heights[:-1] + heights[1:], axis=1)


def _turn(yaw: float, xy: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([c * xy[0] - s * xy[1], s * xy[0] + c * xy[1]])


@dataclass(frozen=True)
class Feet:
    """The ankles of a sequence's skeleton posed without yaw or translation: ``joints`` (N, 24, 3),
    world axes (z up), the body turned only by its pose and root wobble."""

    joints: np.ndarray

    def __post_init__(self):
        joints = np.asarray(self.joints, np.float64)
        if joints.ndim != 3 or joints.shape[1:] != (24, 3):
            raise ValueError(f"Feet needs joints of shape (N, 24, 3), got {joints.shape}")
        object.__setattr__(self, "joints", joints)
        object.__setattr__(self, "_stance", stance_legs(joints) if len(joints) > 1 else np.zeros(0, int))

    def planted_step(self, i: int, yaw_i: float, yaw_next: float) -> np.ndarray:
        """Ground-plane travel (2,) from frame ``i`` to ``i + 1`` that keeps the stance ankle still,
        the body turned by ``yaw_i`` and ``yaw_next`` (radians about z) in the two frames."""
        ankle = ANKLES[int(self._stance[i])]
        here = _turn(yaw_i, self.joints[i, ankle, :2])
        there = _turn(yaw_next, self.joints[i + 1, ankle, :2])
        return here - there  # ground[i+1] + there == ground[i] + here
