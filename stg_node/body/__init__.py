"""Parametric bodies: the SMPL-format body model and the linear-blend-skinning math.

Public interface (everything else is an implementation detail):

- :class:`SmplParams` / :class:`SmplSequence` (:mod:`stg_node.body.params`): SMPL parameters of
  one frame or of a sequence, numpy only (the one type for them across the project);
  :func:`smplx_as_smpl` turns an SMPL-X fit (THuman4.0) into the nearest SMPL parameters;
- :func:`load_body_model` -> :class:`BodyModel`, whose forward gives a :class:`BodyOutput`
  (vertices, joints, bone transforms in world space, ZJU-MoCap's ``Rh``/``Th`` convention);
- :func:`skin_points` / :func:`skin_rotations`: skin arbitrary points and orientations
  (Gaussians) with per-point weights, forward and inverse;
- :data:`BIG_POSE` and :func:`canonical_transforms`: the canonical big pose and the per-joint
  transforms from it to any posed frame;
- :func:`load_smpl_params` / :func:`save_smpl_params` / :func:`drive_body`: read and write SMPL
  pose files (ZJU-MoCap ``new_params`` ``.npy``, ``.npz``) and pose any SMPL-format model with them.

Names are imported on first use, so ``import stg_node.body.params`` (what the bus and the data
types need) does not import torch. The package knows nothing of avatars, datasets or buses.
See docs/BODY.md.
"""

from __future__ import annotations

import importlib

# public name -> the module that defines it
_EXPORTS = {
    "BIG_POSE": "canonical",
    "big_pose_output": "canonical",
    "canonical_transforms": "canonical",
    "nearest_vertex_weights": "canonical",
    "axis_angle_to_matrix": "lbs",
    "blend_transforms": "lbs",
    "matrix_to_axis_angle": "lbs",
    "matrix_to_quaternion": "lbs",
    "quaternion_to_matrix": "lbs",
    "skin_points": "lbs",
    "skin_rotations": "lbs",
    "OPEN_BODY_FILE": "model",
    "BodyModel": "model",
    "BodyOutput": "model",
    "load_body_model": "model",
    "drive_body": "motion",
    "load_smpl_params": "motion",
    "save_smpl_params": "motion",
    "SmplParams": "params",
    "SmplSequence": "params",
    "smplx_as_smpl": "params",
    "SMPL_JOINT_NAMES": "smpl_io",
    "SMPL_PARENTS": "smpl_io",
    "BodyModelError": "smpl_io",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'stg_node.body' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"stg_node.body.{module}"), name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
