"""The canonical "big pose" and the transforms that carry canonical points to any posed frame.

Avatar methods built on SMPL (GauHuman, 3DGS-Avatar) keep their Gaussians in a canonical space
where the legs are spread apart (the "big pose", or Da-pose), so that the thighs do not touch and
skinning weights do not bleed between the legs. :data:`BIG_POSE` is that pose in SMPL's
axis-angle layout; :func:`canonical_transforms` gives, per joint, the rigid transform from the
big-pose canonical space to the posed world:

    T_j = A_j(betas, poses, Rh, Th) @ A_j(betas, BIG_POSE)^-1

Skin canonical points with ``skin_points(x_c, weights, T)``; map posed points back to canonical
space with ``skin_points(x_w, weights, T, inverse=True)`` (or per joint with
``canonical_transforms(..., inverse=True)``, the per-joint inverses ``T_j^-1``).
"""

from __future__ import annotations

import numpy as np
import torch

from stg_node.body.lbs import invert_rigid

# GauHuman / 3DGS-Avatar big pose: hips abducted 45 degrees, ankles rotated back 30 degrees.
BIG_POSE = np.zeros((24, 3), dtype=np.float32)
BIG_POSE[1, 2] = np.deg2rad(45.0)  # left hip
BIG_POSE[2, 2] = -np.deg2rad(45.0)  # right hip
BIG_POSE[7, 2] = -np.deg2rad(30.0)  # left ankle
BIG_POSE[8, 2] = np.deg2rad(30.0)  # right ankle
BIG_POSE.setflags(write=False)


def big_pose_output(model, betas=None):
    """The body in the big pose (model space, no Rh/Th, no pose blend shapes): a BodyOutput whose
    ``vertices`` are the canonical mesh and ``bone_transforms`` map rest -> big pose."""
    poses = torch.tensor(np.array(BIG_POSE), dtype=model.v_template.dtype, device=model.v_template.device)
    return model(betas=betas, poses=poses.reshape(1, 72), pose_blendshapes=False)


def canonical_transforms(
    model, betas=None, poses=None, Rh=None, Th=None, inverse: bool = False
) -> torch.Tensor:
    """Per-joint transforms ``(B, 24, 4, 4)`` from the big-pose canonical space to the posed world.

    With ``inverse=True``, the per-joint inverses (posed world -> canonical). Blend them with
    :func:`stg_node.body.skin_points` and per-point weights. Pose blend shapes are not applied
    (canonical points carry no pose correctives).
    """
    posed = model(betas=betas, poses=poses, Rh=Rh, Th=Th, pose_blendshapes=False).bone_transforms
    big = big_pose_output(model, betas).bone_transforms
    transforms = posed @ invert_rigid(big)
    return invert_rigid(transforms) if inverse else transforms


def nearest_vertex_weights(
    points: torch.Tensor, vertices: torch.Tensor, weights: torch.Tensor, chunk: int = 8192
) -> torch.Tensor:
    """Skinning weights for arbitrary points: those of the nearest mesh vertex.

    ``points (N, 3)``, ``vertices (V, 3)`` (same space, e.g. the big-pose mesh), ``weights (V, 24)``
    -> ``(N, 24)``. Chunked so memory stays at ``chunk * V`` distances.
    """
    out = []
    for start in range(0, points.shape[0], chunk):
        dist = torch.cdist(points[start : start + chunk], vertices)
        out.append(weights[dist.argmin(dim=1)])
    return torch.cat(out) if out else weights.new_zeros(0, weights.shape[1])
