"""Linear blend skinning math shared by every body model (and by the avatar's Gaussians).

Owns the rotation conversions (axis-angle, matrices, wxyz quaternions), the kinematic chain
that turns per-joint rotations into bone transforms, and the skinning of arbitrary points and
their orientations with per-point weights, forward (rest -> posed) and inverse (posed -> rest).

Conventions: a *bone transform* ``A_j`` (4x4) maps a point of the rest (canonical) space to the
posed space as if it were rigidly attached to joint ``j``; a skinned point is
``x' = (sum_j w_j A_j) x``. Everything is batched over a leading ``B`` and vectorised over
points: no Python loop runs over points, only over the 24 joints of the kinematic chain.
"""

from __future__ import annotations

import torch

__all__ = [
    "axis_angle_to_matrix",
    "matrix_to_axis_angle",
    "quaternion_to_matrix",
    "matrix_to_quaternion",
    "rigid_chain",
    "blend_transforms",
    "skin_points",
    "skin_rotations",
    "closest_rotation",
    "inverse_3x3",
    "invert_rigid",
    "make_rigid",
]


def axis_angle_to_matrix(axis_angle: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula: ``(..., 3)`` axis-angle (radians) -> ``(..., 3, 3)`` rotation matrices.

    Exact at zero (a series replaces sin(t)/t and (1-cos t)/t^2 for tiny angles), so gradients
    stay finite at the rest pose.
    """
    if axis_angle.shape[-1] != 3:
        raise ValueError(f"axis-angle must have a last dimension of 3, got shape {tuple(axis_angle.shape)}")
    theta2 = (axis_angle * axis_angle).sum(-1, keepdim=True)
    small = theta2 < 1e-8
    theta2_safe = torch.where(small, torch.ones_like(theta2), theta2)
    theta = theta2_safe.sqrt()
    sinc = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    cosc = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / theta2_safe)
    x, y, z = axis_angle.unbind(-1)
    zero = torch.zeros_like(x)
    skew = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(axis_angle.shape + (3,))
    eye = torch.eye(3, dtype=axis_angle.dtype, device=axis_angle.device)
    return eye + sinc[..., None] * skew + cosc[..., None] * (skew @ skew)


def quaternion_to_matrix(quaternions: torch.Tensor) -> torch.Tensor:
    """``(..., 4)`` quaternions, wxyz (normalised here) -> ``(..., 3, 3)`` rotation matrices."""
    if quaternions.shape[-1] != 4:
        raise ValueError(f"quaternions must be (..., 4) wxyz, got shape {tuple(quaternions.shape)}")
    q = quaternions / quaternions.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip
    return torch.stack(rows, dim=-1).reshape(q.shape[:-1] + (3, 3))


def matrix_to_quaternion(matrices: torch.Tensor) -> torch.Tensor:
    """``(..., 3, 3)`` rotation matrices -> ``(..., 4)`` unit quaternions wxyz with ``w >= 0``.

    Branch-free and stable: all four candidate solutions are formed and the best conditioned one
    (largest denominator) is picked per matrix.
    """
    m = matrices
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    # 4 * q_k^2 for k = w, x, y, z
    q_abs4 = torch.stack(
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], dim=-1
    )
    # 2 |q_k|; the square root's gradient is kept finite at 0 (an unused candidate would otherwise
    # send inf * 0 = NaN back through the gather below).
    q_abs = torch.where(q_abs4 > 0, q_abs4.clamp_min(1e-12).sqrt(), torch.zeros_like(q_abs4))
    candidates = torch.stack(
        [
            torch.stack([q_abs[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01], dim=-1),
            torch.stack([m21 - m12, q_abs[..., 1] ** 2, m10 + m01, m02 + m20], dim=-1),
            torch.stack([m02 - m20, m10 + m01, q_abs[..., 2] ** 2, m21 + m12], dim=-1),
            torch.stack([m10 - m01, m20 + m02, m21 + m12, q_abs[..., 3] ** 2], dim=-1),
        ],
        dim=-2,
    )
    candidates = candidates / (2.0 * q_abs[..., None].clamp_min(0.1))
    best = q_abs.argmax(dim=-1)
    quat = torch.gather(candidates, -2, best[..., None, None].expand(best.shape + (1, 4))).squeeze(-2)
    quat = quat / quat.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return torch.where(quat[..., :1] < 0, -quat, quat)


def matrix_to_axis_angle(matrices: torch.Tensor) -> torch.Tensor:
    """``(..., 3, 3)`` rotation matrices -> ``(..., 3)`` axis-angle with angle in ``[0, pi]``."""
    quat = matrix_to_quaternion(matrices)
    vec = quat[..., 1:]
    sin_half = vec.norm(dim=-1, keepdim=True)
    angle = 2.0 * torch.atan2(sin_half, quat[..., :1])
    scale = torch.where(sin_half < 1e-8, 2.0 * torch.ones_like(sin_half), angle / sin_half.clamp_min(1e-12))
    return vec * scale


def make_rigid(rotations: torch.Tensor, translations: torch.Tensor) -> torch.Tensor:
    """Stack ``(..., 3, 3)`` rotations and ``(..., 3)`` translations into ``(..., 4, 4)`` transforms."""
    top = torch.cat([rotations, translations[..., None]], dim=-1)
    bottom = torch.zeros(top.shape[:-2] + (1, 4), dtype=top.dtype, device=top.device)
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], dim=-2)


def invert_rigid(transforms: torch.Tensor) -> torch.Tensor:
    """Inverse of ``(..., 4, 4)`` rigid transforms (rotation + translation) by transposition."""
    rot_t = transforms[..., :3, :3].transpose(-1, -2)
    return make_rigid(rot_t, -(rot_t @ transforms[..., :3, 3:]).squeeze(-1))


def rigid_chain(
    rotations: torch.Tensor, rest_joints: torch.Tensor, parents: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward kinematics of a tree of joints.

    Args:
        rotations: ``(B, J, 3, 3)`` local rotation of each joint relative to its parent.
        rest_joints: ``(B, J, 3)`` joint positions in the rest pose.
        parents: ``(J,)`` parent index of each joint, ``parents[0] = -1``; parents precede children.

    Returns:
        ``posed_joints (B, J, 3)`` and ``bone_transforms (B, J, 4, 4)``, the transform from rest
        space to posed space of everything rigidly attached to each joint.
    """
    batch, num_joints = rotations.shape[:2]
    parent_list = [int(p) for p in parents.tolist()]
    offsets = rest_joints.clone()
    offsets[:, 1:] = rest_joints[:, 1:] - rest_joints[:, parent_list[1:]]
    local = make_rigid(rotations, offsets)  # (B, J, 4, 4): joint frame -> parent frame
    chain = [local[:, 0]]
    for j in range(1, num_joints):
        chain.append(chain[parent_list[j]] @ local[:, j])
    world = torch.stack(chain, dim=1)  # joint frame (origin at the joint) -> posed space
    posed_joints = world[..., :3, 3]
    # Bone transform: subtract the rest joint so the transform acts on rest-space points.
    shift = (world[..., :3, :3] @ rest_joints[..., None]).squeeze(-1)
    bone_transforms = world.clone()
    bone_transforms[..., :3, 3] = posed_joints - shift
    return posed_joints, bone_transforms


def blend_transforms(weights: torch.Tensor, bone_transforms: torch.Tensor) -> torch.Tensor:
    """Per-point blended transforms ``sum_j w_ij A_bj``: ``(N, J)`` or ``(B, N, J)`` weights,
    ``(B, J, 4, 4)`` transforms -> ``(B, N, 4, 4)``. One matrix product, no loop over points."""
    batch, num_joints = bone_transforms.shape[:2]
    flat = bone_transforms.reshape(batch, num_joints, 16)
    if weights.dim() == 2:
        if weights.shape[1] != num_joints:
            raise ValueError(
                f"weights are (N, {weights.shape[1]}) but there are {num_joints} bone transforms"
            )
        blended = torch.matmul(weights, flat)  # (B, N, 16) by broadcasting
    elif weights.dim() == 3:
        if weights.shape[2] != num_joints:
            raise ValueError(f"weights are {tuple(weights.shape)} but there are {num_joints} bone transforms")
        blended = torch.bmm(weights, flat) if weights.shape[0] == batch else torch.matmul(weights, flat)
    else:
        raise ValueError(f"weights must be (N, J) or (B, N, J), got shape {tuple(weights.shape)}")
    return blended.reshape(blended.shape[:-1] + (4, 4))


def _check_transforms(bone_transforms: torch.Tensor) -> None:
    if bone_transforms.dim() != 4 or bone_transforms.shape[-2:] != (4, 4):
        raise ValueError(f"bone_transforms must be (B, J, 4, 4), got shape {tuple(bone_transforms.shape)}")


def skin_points(
    points: torch.Tensor, weights: torch.Tensor, bone_transforms: torch.Tensor, inverse: bool = False
) -> torch.Tensor:
    """Linear blend skinning of arbitrary points.

    Args:
        points: ``(N, 3)`` (shared by the batch) or ``(B, N, 3)``.
        weights: ``(N, J)`` (or ``(B, N, J)``) skinning weights, rows summing to 1.
        bone_transforms: ``(B, J, 4, 4)`` rest -> posed transforms (e.g. ``BodyOutput.bone_transforms``
            or :func:`stg_node.body.canonical_transforms`).
        inverse: map posed points back to rest space with the inverse of each point's blended
            transform (exact inverse of the forward map for the same weights).

    Returns:
        ``(B, N, 3)`` skinned points.
    """
    _check_transforms(bone_transforms)
    if points.shape[-1] != 3 or points.dim() not in (2, 3):
        raise ValueError(f"points must be (N, 3) or (B, N, 3), got shape {tuple(points.shape)}")
    if points.shape[-2] != weights.shape[-2]:
        raise ValueError(f"{points.shape[-2]} points but {weights.shape[-2]} rows of weights")
    blended = blend_transforms(weights, bone_transforms)
    linear, translation = blended[..., :3, :3], blended[..., :3, 3]
    if inverse:
        return (inverse_3x3(linear) @ (points - translation)[..., None]).squeeze(-1)
    return (linear @ points[..., None]).squeeze(-1) + translation


def _cofactor_and_det(matrices: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Cofactor matrices and determinants of ``(..., 3, 3)`` matrices (``X^-T = cofactor / det``)."""
    a, b, c, d, e, f, g, h, i = matrices.flatten(-2).unbind(-1)
    co00, co01, co02 = e * i - f * h, f * g - d * i, d * h - e * g
    cofactor = torch.stack(
        [
            co00, co01, co02,
            c * h - b * i, a * i - c * g, b * g - a * h,
            b * f - c * e, c * d - a * f, a * e - b * d,
        ],
        dim=-1,
    ).reshape(matrices.shape)  # fmt: skip
    return cofactor, a * co00 + b * co01 + c * co02


def inverse_3x3(matrices: torch.Tensor) -> torch.Tensor:
    """Closed-form inverse of ``(..., 3, 3)`` matrices (adjugate / determinant), vectorised.

    Several times faster than batched LU for millions of tiny matrices; meant for the
    well-conditioned blended skinning matrices (no pivoting, no singularity check).
    """
    cofactor, det = _cofactor_and_det(matrices)
    return cofactor.transpose(-1, -2) / det[..., None, None]


def closest_rotation(matrices: torch.Tensor, iterations: int = 4) -> torch.Tensor:
    """The rotation nearest (Frobenius) to each ``(..., 3, 3)`` matrix: its orthogonal polar factor.

    Scaled Newton iteration ``X <- (g X + X^-T / g) / 2`` with the determinant scaling
    ``g = |det X|^(-1/3)`` (Higham): quadratic convergence, vectorised, and differentiable
    everywhere (unlike an SVD, whose gradient breaks down for the repeated singular values that
    near-rotations have). Blended skinning matrices (singular values within [0.5, 1]) reach
    float64 precision in 4 steps; pass more for matrices further from a rotation.
    """
    x = matrices
    for _ in range(iterations):
        cofactor, det = _cofactor_and_det(x)  # X^-T = cofactor / det
        gamma = det.abs().clamp_min(1e-30).pow(-1.0 / 3.0)[..., None, None]
        x = 0.5 * (gamma * x + cofactor / (gamma * det[..., None, None]))
    return x


def skin_rotations(
    rotations: torch.Tensor, weights: torch.Tensor, bone_transforms: torch.Tensor, inverse: bool = False
) -> torch.Tensor:
    """Rotate per-point orientations (e.g. Gaussians) with the skinning of their points.

    Args:
        rotations: ``(N, 3, 3)`` / ``(B, N, 3, 3)`` matrices, or ``(N, 4)`` / ``(B, N, 4)``
            quaternions wxyz.
        weights: ``(N, J)`` skinning weights; bone_transforms ``(B, J, 4, 4)``.
        inverse: map posed orientations back to rest space.

    Returns:
        The same representation as the input, batched: ``(B, N, 3, 3)`` or ``(B, N, 4)``. The
        blended linear part ``sum_j w_j R_j`` is not exactly a rotation; its polar factor (the
        nearest rotation) is applied. Use :func:`blend_transforms` directly to transform a
        covariance by the exact blended matrix instead.
    """
    _check_transforms(bone_transforms)
    as_quaternions = rotations.shape[-1] == 4
    if as_quaternions:
        matrices = quaternion_to_matrix(rotations)
    elif rotations.shape[-2:] == (3, 3):
        matrices = rotations
    else:
        raise ValueError(
            "rotations must be (..., 3, 3) matrices or (..., 4) wxyz quaternions, "
            f"got {tuple(rotations.shape)}"
        )
    blended = closest_rotation(blend_transforms(weights, bone_transforms)[..., :3, :3])
    if inverse:
        blended = blended.transpose(-1, -2)
    out = blended @ matrices
    return matrix_to_quaternion(out) if as_quaternions else out
