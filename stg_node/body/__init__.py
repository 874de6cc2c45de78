"""Parametric bodies: the SMPL-format body model and the linear-blend-skinning math.

Public interface (everything else is an implementation detail):

- :func:`load_body_model` -> :class:`BodyModel`, whose forward gives a :class:`BodyOutput`
  (vertices, joints, bone transforms in world space, ZJU-MoCap's ``Rh``/``Th`` convention);
- :func:`skin_points` / :func:`skin_rotations`: skin arbitrary points and orientations
  (Gaussians) with per-point weights, forward and inverse;
- :data:`BIG_POSE` and :func:`canonical_transforms`: the canonical big pose and the per-joint
  transforms from it to any posed frame;
- :func:`load_smpl_params` / :func:`drive_body`: read SMPL pose files (ZJU-MoCap ``new_params``
  ``.npy``, ``.npz``) and pose any SMPL-format model with them.

The package knows nothing of avatars, datasets or buses. See docs/BODY.md.
"""

from stg_node.body.canonical import BIG_POSE, big_pose_output, canonical_transforms, nearest_vertex_weights
from stg_node.body.lbs import (
    axis_angle_to_matrix,
    blend_transforms,
    matrix_to_axis_angle,
    matrix_to_quaternion,
    quaternion_to_matrix,
    skin_points,
    skin_rotations,
)
from stg_node.body.model import OPEN_BODY_FILE, BodyModel, BodyOutput, load_body_model
from stg_node.body.motion import SmplMotion, drive_body, load_smpl_params, procedural_walk, save_smpl_params
from stg_node.body.smpl_io import SMPL_JOINT_NAMES, SMPL_PARENTS, BodyModelError

__all__ = [
    "BIG_POSE",
    "OPEN_BODY_FILE",
    "SMPL_JOINT_NAMES",
    "SMPL_PARENTS",
    "BodyModel",
    "BodyModelError",
    "BodyOutput",
    "SmplMotion",
    "axis_angle_to_matrix",
    "big_pose_output",
    "blend_transforms",
    "canonical_transforms",
    "drive_body",
    "load_body_model",
    "load_smpl_params",
    "matrix_to_axis_angle",
    "matrix_to_quaternion",
    "nearest_vertex_weights",
    "procedural_walk",
    "save_smpl_params",
    "quaternion_to_matrix",
    "skin_points",
    "skin_rotations",
]
