"""Keypoint layouts and where each of their points sits on an SMPL-format body.

A layout names a detector's output points in order. Fitting pairs each *fit target* with one
body point (an SMPL joint or a surface landmark, see body_points.py) and with the mean of one
or more detector points; its weight says how well the two agree in general (a network's "hip"
is near, but not exactly at, SMPL's hip joint; the face points are small and often wrong).

- ``blazepose33``: MediaPipe BlazePose's 33 landmarks (the shipped detector).
- ``coco17``: the COCO keypoints most ONNX pose models output (RTMPose, ViTPose, ...).
- ``smpl24``: SMPL's own 24 joints, for ground-truth projections in tests and evaluation.
"""

from __future__ import annotations

from dataclasses import dataclass

from stg_node.body.smpl_io import SMPL_JOINT_NAMES
from stg_node.tracking.blazepose import BLAZEPOSE_NAMES
from stg_node.tracking.body_points import JOINT_INDEX, PointSpec

# COCO's 17 keypoints carry BlazePose's names for the same points, in COCO's order.
COCO17_NAMES = tuple(
    BLAZEPOSE_NAMES[i] for i in (0, 2, 5, 7, 8, 11, 12, 13, 14, 15, 16, 23, 24, 25, 26, 27, 28)
)

# Limb joints named alike in SMPL and the detectors, with their weight.
_LIMB_JOINTS = {
    "left_shoulder": 1.0,
    "right_shoulder": 1.0,
    "left_elbow": 1.0,
    "right_elbow": 1.0,
    "left_wrist": 1.0,
    "right_wrist": 1.0,
    "left_hip": 1.0,
    "right_hip": 1.0,
    "left_knee": 1.0,
    "right_knee": 1.0,
    "left_ankle": 1.0,
    "right_ankle": 1.0,
}
# Body segments whose 3D direction a network's metric ("world") points tell the fitter: limbs
# and the torso frame, by fit-target name (pairs missing from a layout are skipped).
WORLD_BONES = (
    ("left_shoulder", "left_elbow"),
    ("left_elbow", "left_wrist"),
    ("right_shoulder", "right_elbow"),
    ("right_elbow", "right_wrist"),
    ("left_hip", "left_knee"),
    ("left_knee", "left_ankle"),
    ("right_hip", "right_knee"),
    ("right_knee", "right_ankle"),
    ("left_hip", "right_hip"),
    ("left_shoulder", "right_shoulder"),
    ("left_hip", "left_shoulder"),
    ("right_hip", "right_shoulder"),
    ("left_ankle", "left_toe"),
    ("right_ankle", "right_toe"),
    # Not the palm (wrist to knuckles, knuckle to knuckle) nor the sole (heel to toe): BlazePose's
    # metric points get them wrong by 44-58 and 33-36 degrees (median, the benchmark's mixed
    # motion at 256 px), and as directions they made the tracked twists worse (docs/TRACKING.md).
    ("left_ear", "right_ear"),
)
_FACE_WEIGHT = 0.3
_FACE = ("nose", "left_eye", "right_eye", "left_ear", "right_ear")
_EXTREMITY_WEIGHT = 0.5
_THUMB_WEIGHT = 0.3  # BlazePose's thumb point is the thumb's second knuckle, the landmark its tip


@dataclass(frozen=True)
class FitTarget:
    """One fitted correspondence: the mean of detector points ``sources`` <-> body point ``point``."""

    point: PointSpec
    sources: tuple[int, ...]
    weight: float


@dataclass(frozen=True)
class KeypointLayout:
    name: str
    names: tuple[str, ...]
    targets: tuple[FitTarget, ...]
    # Detector points whose midpoint is the body's root for root-relative (world) comparisons.
    root_sources: tuple[int, ...]

    def bones(self) -> list[tuple[int, int]]:
        """:data:`WORLD_BONES` as pairs of target indices (those this layout has)."""
        index = {t.point.name: i for i, t in enumerate(self.targets)}
        return [(index[a], index[b]) for a, b in WORLD_BONES if a in index and b in index]

    @property
    def num_points(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        return self.names.index(name)


def _limbs_and_face(names: tuple[str, ...]) -> list[FitTarget]:
    targets = [
        FitTarget(PointSpec(name, joint=JOINT_INDEX[name]), (names.index(name),), weight)
        for name, weight in _LIMB_JOINTS.items()
    ]
    targets += [
        FitTarget(PointSpec(name, landmark=name), (names.index(name),), _FACE_WEIGHT) for name in _FACE
    ]
    return targets


def _blazepose33() -> KeypointLayout:
    names = BLAZEPOSE_NAMES
    targets = _limbs_and_face(names)
    for side in ("left", "right"):
        # BlazePose's index and pinky points sit on the knuckles either side of SMPL's hand joint,
        # its thumb point on the thumb: each its own surface landmark (body_points.hand_landmarks),
        # so the palm's line (index to pinky) turns the forearm about its own axis. Their mean,
        # the one hand point this once was, stays where it was.
        for finger, weight in (
            ("index", _EXTREMITY_WEIGHT),
            ("pinky", _EXTREMITY_WEIGHT),
            ("thumb", _THUMB_WEIGHT),
        ):
            targets.append(
                FitTarget(PointSpec(f"{side}_{finger}", landmark=f"{side}_{finger}"),
                          (names.index(f"{side}_{finger}"),), weight)
            )  # fmt: skip
        targets.append(
            FitTarget(
                PointSpec(f"{side}_heel", landmark=f"{side}_heel"),
                (names.index(f"{side}_heel"),),
                _EXTREMITY_WEIGHT,
            )
        )
        targets.append(
            FitTarget(
                PointSpec(f"{side}_toe", landmark=f"{side}_toe"),
                (names.index(f"{side}_foot_index"),),
                _EXTREMITY_WEIGHT,
            )
        )
    root = (names.index("left_hip"), names.index("right_hip"))
    return KeypointLayout("blazepose33", names, tuple(targets), root)


def _coco17() -> KeypointLayout:
    names = COCO17_NAMES
    root = (names.index("left_hip"), names.index("right_hip"))
    return KeypointLayout("coco17", names, tuple(_limbs_and_face(names)), root)


def _smpl24() -> KeypointLayout:
    names = tuple(SMPL_JOINT_NAMES)
    targets = tuple(FitTarget(PointSpec(name, joint=j), (j,), 1.0) for j, name in enumerate(names))
    return KeypointLayout("smpl24", names, targets, (JOINT_INDEX["left_hip"], JOINT_INDEX["right_hip"]))


LAYOUTS = {layout.name: layout for layout in (_blazepose33(), _coco17(), _smpl24())}


def get_layout(name: str) -> KeypointLayout:
    try:
        return LAYOUTS[name]
    except KeyError:
        raise ValueError(f"unknown keypoint layout {name!r}; known: {', '.join(LAYOUTS)}") from None
