"""Where a detector's keypoints sit on an SMPL body: offsets from the SMPL points the layouts name.

A pose network's "hip" is not SMPL's hip joint: the annotators of its training images marked the
hip where it shows (on the side of the pelvis, higher and more to the front than the joint
centre SMPL's regressor places), the "shoulder" on the top of the shoulder, the "ankle" on the
ankle bones, the "ear" on the ear. One camera cannot see these few centimetres; several can, and
a fit that ignores them bends the body to make up for them (measured: the triangulated BlazePose
keypoints of four cameras lie 1-5 cm from the SMPL points the layout pairs them with, nearly the
same offset in every frame).

:data:`OFFSETS` gives, per layout and fit target, the offset in the rest axes of a carrier joint
(the bone the point moves with): the median, over every frame of synthetic sequences the
evaluation does not use (other seeds and motions; ``python tools/fit_keypoint_offsets.py``), of
``R_carrier^T (triangulated keypoint - SMPL point)``. :class:`~stg_node.tracking.body_points
.BodyKeypoints` moves its points by them; the multi-view fit uses them (a single view's fit does
not: there the depth of a point is a guess anyway).

``tools/fit_keypoint_offsets.py`` measures them and prints a new table.
"""

from __future__ import annotations

from stg_node.body.smpl_io import SMPL_JOINT_NAMES
from stg_node.tracking.layouts import KeypointLayout

JOINT = {name: i for i, name in enumerate(SMPL_JOINT_NAMES)}
# The bone each landmark moves with.
LANDMARK_CARRIERS = {
    "nose": "head",
    "left_eye": "head",
    "right_eye": "head",
    "left_ear": "head",
    "right_ear": "head",
    "left_heel": "left_ankle",
    "right_heel": "right_ankle",
    "left_toe": "left_ankle",
    "right_toe": "right_ankle",
    "left_index": "left_wrist",
    "right_index": "right_wrist",
    "left_pinky": "left_wrist",
    "right_pinky": "right_wrist",
    "left_thumb": "left_wrist",
    "right_thumb": "right_wrist",
}

# layout -> fit target -> (carrier joint name, offset in metres in the carrier's rest axes:
# x = the body's left, y = up, z = front). Measured by `python tools/fit_keypoint_offsets.py`
# (its defaults: stg-synth seeds 11, 12, 13 with the dance, walk and turn motions, 90 frames
# at 512 px, four cameras 90 degrees apart; BlazePose full under LiteRT); the comment gives how far
# the three sequences' medians lie from the pooled one. Regenerate when the detector or the
# layouts change.
OFFSETS: dict[str, dict[str, tuple[str, tuple[float, float, float]]]] = {
    "blazepose33": {
        "left_shoulder": ("left_collar", (-0.0041, 0.0324, 0.0057)),  # sequences differ by <= 18 mm
        "right_shoulder": ("right_collar", (0.0074, 0.0315, 0.0019)),  # sequences differ by <= 17 mm
        "left_elbow": ("left_shoulder", (-0.0177, 0.0057, 0.0196)),  # sequences differ by <= 13 mm
        "right_elbow": ("right_shoulder", (0.0251, -0.0002, 0.0150)),  # sequences differ by <= 16 mm
        "left_wrist": ("left_elbow", (0.0115, 0.0016, -0.0003)),  # sequences differ by <= 6 mm
        "right_wrist": ("right_elbow", (-0.0098, -0.0039, 0.0009)),  # sequences differ by <= 4 mm
        "left_hip": ("pelvis", (-0.0149, -0.0001, 0.0293)),  # sequences differ by <= 7 mm
        "right_hip": ("pelvis", (0.0185, -0.0017, 0.0279)),  # sequences differ by <= 8 mm
        "left_knee": ("left_hip", (-0.0147, 0.0000, -0.0030)),  # sequences differ by <= 10 mm
        "right_knee": ("right_hip", (0.0158, -0.0021, -0.0041)),  # sequences differ by <= 10 mm
        "left_ankle": ("left_knee", (-0.0074, 0.0295, 0.0018)),  # sequences differ by <= 9 mm
        "right_ankle": ("right_knee", (0.0044, 0.0320, -0.0016)),  # sequences differ by <= 6 mm
        "nose": ("head", (0.0042, 0.0147, -0.0223)),  # sequences differ by <= 11 mm
        "left_eye": ("head", (0.0056, -0.0049, -0.0242)),  # sequences differ by <= 7 mm
        "right_eye": ("head", (0.0001, -0.0047, -0.0238)),  # sequences differ by <= 8 mm
        "left_ear": ("head", (-0.0312, -0.0079, 0.0391)),  # sequences differ by <= 4 mm
        "right_ear": ("head", (0.0358, -0.0076, 0.0389)),  # sequences differ by <= 5 mm
        "left_heel": ("left_ankle", (-0.0173, 0.0293, 0.0143)),  # sequences differ by <= 11 mm
        "left_toe": ("left_ankle", (0.0213, 0.0147, -0.0247)),  # sequences differ by <= 10 mm
        "right_heel": ("right_ankle", (0.0157, 0.0313, 0.0120)),  # sequences differ by <= 11 mm
        "right_toe": ("right_ankle", (-0.0168, 0.0088, -0.0245)),  # sequences differ by <= 9 mm
        # The hand's index, pinky and thumb points (separate since the palm's twist was fitted;
        # before, their mean sat 1.2-1.6 cm from SMPL's hand joint) are not measured yet.
    },
}


def carrier(layout: KeypointLayout, target_index: int, parents) -> int:
    """The joint whose rotation a target's offset turns with: a joint's parent, a landmark's bone."""
    point = layout.targets[target_index].point
    if point.joint is not None:
        return int(parents[point.joint]) if point.joint > 0 else 0
    return JOINT[LANDMARK_CARRIERS[point.landmark]]


def offsets_for(layout: KeypointLayout) -> dict[str, tuple[int, tuple[float, float, float]]]:
    """The :class:`BodyKeypoints` ``offsets`` argument for ``layout`` (empty when none were measured)."""
    table = OFFSETS.get(layout.name, {})
    return {name: (JOINT[joint], tuple(vector)) for name, (joint, vector) in table.items()}
