"""The rigid part of the deformation: linear blend skinning of the Gaussians by the body's bones.

``X_L = sum_b w_b B_b x_c``: each Gaussian's canonical (big-pose) centre is carried to the posed
world by the blend of its bones' transforms. Its orientation turns with the normalised blend of
its bones' rotation quaternions (``normalise(sum_b w_b q_b)``, the rotational part of dual
quaternion skinning, with the 24 joint quaternions put in one hemisphere along the kinematic
chain): one (N, 24) x (24, 4) product, where the polar factor of the blended matrix
(stg_node.body.skin_rotations) costs several Newton iterations per Gaussian and its gradient.
The two agree to first order and exactly for a Gaussian bound to one bone.

:class:`Skeleton` holds only what forward kinematics needs (the subject's rest joints, the
parent table and the inverse big-pose transforms), not the mesh, so a renderer rebuilds it from
a GaussianSnapshot alone and a training step never touches the 13k-vertex body.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from stg_node.avatar import kernels, kinematics
from stg_node.body import lbs
from stg_node.body.canonical import big_pose_output

SKIN_WEIGHT_EPS = 1e-4  # floor added to the body's weights before the learned correction (blend_weights)
QUAT_EPS = 1e-12  # quaternions shorter than this are not divided by their norm


@dataclass
class PosedBones:
    """One frame's bones, canonical big pose -> world."""

    transforms: torch.Tensor  # (1, 24, 4, 4)
    quats: torch.Tensor  # (1, 24, 4) wxyz rotations of the transforms, one hemisphere along the chain

    @classmethod
    def from_transforms(cls, transforms: torch.Tensor, parents: list[int]) -> PosedBones:
        quats = lbs.matrix_to_quaternion(transforms[..., :3, :3])
        return cls(transforms, quats * hemisphere_signs(quats, parents))

    def detach(self) -> PosedBones:
        return PosedBones(self.transforms.detach(), self.quats.detach())


class Skeleton(torch.nn.Module):
    """Forward kinematics of the subject's body from its rest joints (no mesh)."""

    def __init__(self, rest_joints: torch.Tensor, parents: torch.Tensor, big_pose_inverse: torch.Tensor):
        super().__init__()
        if rest_joints.shape != (24, 3) or parents.shape != (24,) or big_pose_inverse.shape != (24, 4, 4):
            raise ValueError(
                "Skeleton needs rest_joints (24, 3), parents (24,), big_pose_inverse (24, 4, 4); got "
                f"{tuple(rest_joints.shape)}, {tuple(parents.shape)}, {tuple(big_pose_inverse.shape)}"
            )
        self.register_buffer("rest_joints", rest_joints.float())
        self.register_buffer("parents", parents.long())
        self.register_buffer("big_pose_inverse", big_pose_inverse.float())
        self.parent_list = [int(p) for p in parents.tolist()]

    @classmethod
    def from_body(cls, body, betas) -> Skeleton:
        """The skeleton of ``body`` (a stg_node.body.BodyModel) with shape ``betas``."""
        with torch.no_grad():
            big = big_pose_output(body, betas)
            return cls(big.rest_joints[0], body.parents, lbs.invert_rigid(big.bone_transforms[0]))

    def bones(self, poses: torch.Tensor, Rh: torch.Tensor, Th: torch.Tensor) -> PosedBones:
        """Canonical -> world transforms for ``poses (B, 24, 3)``, ``Rh (B, 3)``, ``Th (B, 3)``.

        Same convention as stg_node.body (world = R(Rh) @ smpl + Th): equal to
        ``stg_node.body.canonical_transforms`` without pose blend shapes.
        """
        if not (torch.is_grad_enabled() and (poses.requires_grad or Rh.requires_grad or Th.requires_grad)):
            return self._bones_without_grad(poses, Rh, Th)
        if kernels.mode() != "torch" and poses.device.type == "cpu":  # the hand-written backward
            return PosedBones(*kinematics.bones(self, poses, Rh, Th))
        batch = poses.shape[0]
        rotations = lbs.axis_angle_to_matrix(poses.reshape(batch, 24, 3))
        rest = self.rest_joints.expand(batch, 24, 3)
        _, local = lbs.rigid_chain(rotations, rest, self.parents)
        world = lbs.make_rigid(lbs.axis_angle_to_matrix(Rh), Th)
        return PosedBones.from_transforms(world[:, None] @ local @ self.big_pose_inverse, self.parent_list)

    def _bones_without_grad(self, poses: torch.Tensor, Rh: torch.Tensor, Th: torch.Tensor) -> PosedBones:
        """:meth:`bones` where no gradient is wanted (a renderer's frames, a training frame's fixed
        bones): the same kinematics on 24 joints in float64 numpy (kinematics.forward_kinematics),
        about half the cost of the ~150 small torch ops (and their autograd bookkeeping) of the
        differentiable path."""
        batch = poses.shape[0]
        transforms, _ = kinematics.forward_kinematics(
            kinematics.as_float64(poses).reshape(batch, 24, 3),
            kinematics.as_float64(Rh).reshape(batch, 3),
            kinematics.as_float64(Th).reshape(batch, 3),
            kinematics.as_float64(self.rest_joints),
            self.parent_list,
            kinematics.as_float64(self.big_pose_inverse),
        )
        dtype = torch.promote_types(self.rest_joints.dtype, poses.dtype)
        out = torch.as_tensor(transforms, device=self.rest_joints.device).to(dtype)
        return PosedBones.from_transforms(out, self.parent_list)


def hemisphere_signs(quats: torch.Tensor, parents: list[int]) -> torch.Tensor:
    """(B, J, 1) signs +-1 that put each joint's quaternion of ``quats`` (B, J, 4) in its parent's
    hemisphere (the parent's already flipped), root first. Constants for the gradient, so found
    without it: one numpy loop over the joints instead of ~100 autograd nodes a frame."""
    sign = kinematics.hemisphere_signs(kinematics.as_float64(quats), parents)
    return torch.as_tensor(sign, dtype=quats.dtype, device=quats.device)


def blend_weights(skin_weights: torch.Tensor, skin_delta: torch.Tensor | None) -> torch.Tensor:
    """Effective weights: the body's, corrected in log space by the learned delta (rows sum to 1).

    ``w = (w_body + eps) exp(delta) / sum(...)``; eps lets a bone the body gave no weight gain some.
    Without a delta the body's weights are used unchanged.
    """
    if skin_delta is None:
        return skin_weights
    w = (skin_weights + SKIN_WEIGHT_EPS) * skin_delta.exp()
    return w / w.sum(dim=1, keepdim=True)


@dataclass
class Skinned:
    """One frame's skinning of N canonical points."""

    means: torch.Tensor  # (N, 3) world centres
    quats: torch.Tensor  # (N, 4) unit wxyz: the blended bone rotation of each point
    blended: torch.Tensor  # (N, 4, 4) the blended transform itself


def blend(weights: torch.Tensor, bones: PosedBones) -> torch.Tensor:
    """Per-point blended transforms ``(N, 4, 4)`` of one frame (one matrix product)."""
    if bones.transforms.shape[0] != 1:
        raise ValueError("blend() poses one frame at a time")
    return (weights @ bones.transforms[0].reshape(-1, 16)).reshape(-1, 4, 4)


def blend_rotation(weights: torch.Tensor, bones: PosedBones) -> torch.Tensor:
    """Per-point rotation ``(N, 4)``: the normalised weighted sum of the bones' quaternions."""
    q = weights @ bones.quats[0]
    return q / q.norm(dim=1, keepdim=True).clamp_min(QUAT_EPS)


JOINT_SHRINK_FLOOR = 0.05  # a Gaussian between bones that point opposite ways keeps 5 % of its size


def joint_shrink(weights: torch.Tensor, bones: PosedBones, floor: float = JOINT_SHRINK_FLOOR) -> torch.Tensor:
    """(N,) how much linear blend skinning squeezes the body around each point, in ``(floor, 1]``.

    A point between two bones takes the blend of their transforms, ``M = sum_b w_b R_b``, which is a
    rotation only when the bones agree; where they bend apart ``M`` squeezes the surface (the mesh
    thins at a bent elbow). Skinning turns a Gaussian by the rotation of the blend and keeps its
    size (``skin``): a Gaussian that straddles an elbow folded far beyond training keeps its full
    extent while the surface around it collapses, and sticks out of the limb as a streak. Its size
    follows the surface instead when scaled by the squeeze of ``M``. For two bones turned by ``t``
    about one axis with weights 1/2 the blended quaternion has norm ``|q| = cos(t/4)`` and ``M``
    shrinks the plane of the bend by ``cos(t/2) = 2|q|^2 - 1``; that closed form, computed from the
    blended quaternion of any number of bones, is the factor: 1 for a point on one bone or bones
    that agree (every Gaussian away from the joints, and at joints bent as in a relaxed pose it is
    within a few percent of 1), falling as the bones part. No gradient: it is the body's, not learnt.
    """
    with torch.no_grad():
        q = weights.detach() @ bones.quats[0]
        return squeeze_of_blend(q.pow(2).sum(dim=1), floor)


def squeeze_of_blend(norm2: torch.Tensor, floor: float = JOINT_SHRINK_FLOOR) -> torch.Tensor:
    """:func:`joint_shrink` from the squared norms (N,) of the blended quaternions (the fused
    skinning kernel gives them as it blends)."""
    return (2.0 * norm2 - 1.0).clamp(floor, 1.0)


def skin(means: torch.Tensor, weights: torch.Tensor, bones: PosedBones, rotations: bool = True) -> Skinned:
    """Centres (and, with ``rotations``, orientations) of canonical points under one frame's bones."""
    blended = blend(weights, bones)
    world = (blended[:, :3, :3] @ means[..., None]).squeeze(-1) + blended[:, :3, 3]
    quats = blend_rotation(weights, bones) if rotations else None
    return Skinned(world, quats, blended)


def skin_with_kernel(
    means: torch.Tensor,
    skin_weights: torch.Tensor,
    skin_delta: torch.Tensor | None,
    bones: PosedBones,
    *,
    local_quats: torch.Tensor | None = None,
    camera_center: torch.Tensor | None = None,
    rotations: bool = True,
    blend_norms: bool = False,
    next_bones: PosedBones | None = None,
    next_means: torch.Tensor | None = None,
):
    """The fused C++ skinning of ``means`` (stg_node.splat.skin_ops): ``blend_weights`` + ``skin``
    (+ the local rotation and the canonical view direction, see AvatarModel.pose) in one pass,
    or None where the kernel does not apply (kernels.use_kernels); the caller then runs torch.
    ``next_bones``: also the centres (``next_means``, default ``means``) under another frame's
    bones with the same weights (``.next_means``; skin_ops.skin's second frame)."""
    if bones.transforms.shape[0] != 1 or (next_bones is not None and next_bones.transforms.shape[0] != 1):
        raise ValueError("skin_with_kernel() poses one frame at a time")
    next_transforms = None if next_bones is None else next_bones.transforms
    if not kernels.use_kernels(
        means,
        skin_weights,
        skin_delta,
        local_quats,
        bones.transforms,
        bones.quats,
        next_transforms,
        next_means,
    ):
        return None
    from stg_node.splat import skin_ops

    return skin_ops.skin(
        means,
        skin_weights,
        bones.transforms[0],
        bones.quats[0],
        weight_eps=SKIN_WEIGHT_EPS,
        quat_eps=QUAT_EPS,
        skin_delta=skin_delta,
        local_quats=local_quats,
        camera_center=camera_center,
        rotations=rotations,
        blend_norms=blend_norms,
        next_bone_transforms=None if next_transforms is None else next_transforms[0],
        next_means=next_means,
    )
