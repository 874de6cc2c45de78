"""Differentiable forward kinematics of the skeleton with a hand-written backward (CPU, float64).

A training step that refines the body's pose differentiates the 24 bones (``Skeleton.bones``):
through autograd that is ~150 small torch ops forward (Rodrigues, the kinematic chain, the
quaternions of the bones) and as many nodes backward, each on a handful of numbers, so the cost is
all per-op overhead. Here the forward is the numpy float64 kinematics the gradient-free path
already uses, and the backward is the chain rule written out over the 24 joints:

- the bones' quaternions q_j of rotations R_j: every perturbation reaching R_j is a rotation's
  (the chain multiplies rotations), dR = [w]x R, for which dq = 1/2 (0, w) * q; so dL/dq is
  carried as the matrix gradient [h/4]x R with h = -g_w q_v + q_w g_v + q_v x g_v, which gives
  <G, dR> = <g, dq> on every such perturbation (the quaternion extraction's branches and the
  hemisphere signs need no derivative of their own);
- T_j = root A_j B_j^-1, A_j = W_j [I, -rest_j; 0, 1], W_j = W_parent(j) local_j: products of 4x4
  matrices, back along the chain from the leaves;
- a rotation's gradient G to its axis-angle p: J_l(p)^T vee(G R^T - R G^T) with SO(3)'s left
  Jacobian J_l (its small-angle series near zero, like lbs.axis_angle_to_matrix).

The torch path (``rigid.Skeleton.bones`` under ``kernels.reference()``) is the oracle it is tested
against in float64. Where the CPU kernels build, the same maths runs in one C++ pass
(``csrc/kinematics.cpp``, float64): numpy's per-call overhead on a few hundred operations on 4x4
matrices was ~1.4 ms of a training step; the numpy functions here are its reference
(:func:`numpy_reference` switches the kernel off, for the tests).
"""

from __future__ import annotations

import contextlib
import threading

import numpy as np
import torch

_local = threading.local()


@contextlib.contextmanager
def numpy_reference():
    """Run the numpy kinematics (the C++ kernel's reference) inside this block, in this thread."""
    previous = getattr(_local, "numpy", False)
    _local.numpy = True
    try:
        yield
    finally:
        _local.numpy = previous


def _kernel_ops():
    """The CPU kernels' operators for the kinematics, or None (not built here, or numpy asked for)."""
    if getattr(_local, "numpy", False):
        return None
    from stg_node.splat.build import load_kernels
    from stg_node.splat.types import BackendUnavailable

    try:
        return load_kernels().ops
    except BackendUnavailable:
        return None


def as_float64(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().numpy().astype(np.float64)


def _skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    zero = np.zeros_like(x)
    return np.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=-1).reshape(v.shape + (3,))


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross products over the last axis (np.cross costs ~10x more on a few dozen vectors)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def rodrigues(axis_angle: np.ndarray) -> np.ndarray:
    """lbs.axis_angle_to_matrix in numpy (the same small-angle series)."""
    theta2 = (axis_angle * axis_angle).sum(-1)[..., None]
    small = theta2 < 1e-8
    safe = np.where(small, 1.0, theta2)
    theta = np.sqrt(safe)
    sinc = np.where(small, 1.0 - theta2 / 6.0, np.sin(theta) / theta)
    cosc = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(theta)) / safe)
    skew = _skew(axis_angle)
    return np.eye(3) + sinc[..., None] * skew + cosc[..., None] * (skew @ skew)


def _left_jacobian_t_times(axis_angle: np.ndarray, w: np.ndarray) -> np.ndarray:
    """J_l(p)^T w for (..., 3) axis-angles p: the gradient of p when dL = w . omega, dR = [omega]x R."""
    theta2 = (axis_angle * axis_angle).sum(-1)[..., None]
    small = theta2 < 1e-8
    safe = np.where(small, 1.0, theta2)
    theta = np.sqrt(safe)
    a = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(theta)) / safe)
    b = np.where(small, 1.0 / 6.0 - theta2 / 120.0, (theta - np.sin(theta)) / (safe * theta))
    # J = I + a [p]x + b [p]x^2; J^T w = w - a p x w + b [p]x^2 w ([p]x^2 is symmetric)
    pxw = _cross(axis_angle, w)
    return w - a * pxw + b * _cross(axis_angle, pxw)


def _rotation_grad(G: np.ndarray, R: np.ndarray) -> np.ndarray:
    """(..., 3) w with <G, [omega]x R> = w . omega for (..., 3, 3) gradients G of rotations R."""
    M = G @ np.swapaxes(R, -1, -2)
    pairs = ((2, 1, 1, 2), (0, 2, 2, 0), (1, 0, 0, 1))
    return np.stack([M[..., a, b] - M[..., c, d] for a, b, c, d in pairs], -1)


def matrix_to_quaternion(m: np.ndarray) -> np.ndarray:
    """lbs.matrix_to_quaternion in numpy: (..., 3, 3) rotations -> (..., 4) unit wxyz, w >= 0, from
    the best conditioned of the four candidate solutions (the same formulas; ~40 torch ops on 24
    matrices cost more than the kinematics)."""
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    q_abs4 = np.stack(
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1
    )
    q_abs = np.sqrt(np.maximum(q_abs4, 0.0))
    candidates = np.stack(
        [
            np.stack([q_abs[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01], -1),
            np.stack([m21 - m12, q_abs[..., 1] ** 2, m10 + m01, m02 + m20], -1),
            np.stack([m02 - m20, m10 + m01, q_abs[..., 2] ** 2, m21 + m12], -1),
            np.stack([m10 - m01, m20 + m02, m21 + m12, q_abs[..., 3] ** 2], -1),
        ],
        -2,
    )
    candidates = candidates / (2.0 * np.maximum(q_abs[..., None], 0.1))
    best = q_abs.argmax(-1)
    quat = np.take_along_axis(candidates, best[..., None, None], axis=-2)[..., 0, :]
    quat = quat / np.maximum(np.linalg.norm(quat, axis=-1, keepdims=True), 1e-12)
    return np.where(quat[..., :1] < 0, -quat, quat)


def hemisphere_signs(quats: np.ndarray, parents) -> np.ndarray:
    """rigid.hemisphere_signs on a numpy (B, J, 4) array: (B, J, 1) signs +-1."""
    sign = np.ones(quats.shape[:2])
    for j in range(1, quats.shape[1]):
        parent = parents[j]
        sign[:, j] = np.where((quats[:, j] * quats[:, parent]).sum(-1) * sign[:, parent] < 0, -1.0, 1.0)
    return sign[..., None]


def forward_kinematics(poses: np.ndarray, Rh: np.ndarray, Th: np.ndarray, rest: np.ndarray, parents, big_inv):
    """Float64 kinematics of ``poses (B, 24, 3)``, ``Rh (B, 3)``, ``Th (B, 3)``: (transforms (B, J, 4,
    4) canonical -> world, and what the backward pass needs: local (B, J, 4, 4) joint -> parent,
    world (B, J, 4, 4) joint -> posed, bone (B, J, 4, 4) rest -> posed, root (B, 4, 4))."""
    batch, joints = poses.shape[:2]
    offsets = rest.copy()
    offsets[1:] -= rest[parents[1:]]
    local = np.zeros((batch, joints, 4, 4))
    local[..., :3, :3] = rodrigues(poses)
    local[..., :3, 3] = offsets
    local[..., 3, 3] = 1.0
    world = np.empty_like(local)
    world[:, 0] = local[:, 0]
    for j in range(1, joints):
        world[:, j] = world[:, parents[j]] @ local[:, j]
    bone = world.copy()
    bone[..., :3, 3] -= (world[..., :3, :3] @ rest[..., None])[..., 0]  # act on rest-space points
    root = np.zeros((batch, 4, 4))
    root[:, :3, :3] = rodrigues(Rh)
    root[:, :3, 3] = Th
    root[:, 3, 3] = 1.0
    transforms = root[:, None] @ bone @ big_inv
    return transforms, (local, world, bone, root)


class _Bones(torch.autograd.Function):
    @staticmethod
    def forward(ctx, poses, Rh, Th, skeleton):
        batch = poses.shape[0]
        rest = as_float64(skeleton.rest_joints)
        big_inv = as_float64(skeleton.big_pose_inverse)
        p = as_float64(poses).reshape(batch, 24, 3)
        rh, th = as_float64(Rh).reshape(batch, 3), as_float64(Th).reshape(batch, 3)
        ops = _kernel_ops()
        if ops is not None:
            parents = skeleton.parents.detach().cpu().long().contiguous()
            arrays = [torch.from_numpy(np.ascontiguousarray(a)) for a in (p, rh, th, rest, big_inv)]
            transforms, quats, *saved = (
                t.numpy() for t in ops.kin_bones_fwd(*arrays[:4], parents, arrays[4])
            )
        else:
            transforms, saved = forward_kinematics(p, rh, th, rest, skeleton.parent_list, big_inv)
            quats = matrix_to_quaternion(transforms[..., :3, :3])
            quats = quats * hemisphere_signs(quats, skeleton.parent_list)
        dtype = torch.promote_types(skeleton.rest_joints.dtype, poses.dtype)
        out = torch.as_tensor(transforms, device=poses.device).to(dtype)
        out_quats = torch.as_tensor(quats, device=poses.device).to(dtype)
        ctx.fk = (p, rh, rest, big_inv, skeleton.parent_list, transforms, quats, *saved)
        ctx.shapes = (poses.shape, Rh.shape, Th.shape, poses.dtype)
        ctx.ops = ops
        return out, out_quats

    @staticmethod
    def backward(ctx, g_transforms, g_quats):
        p, rh, rest, big_inv, parents, transforms, quats, local, world, bone, root = ctx.fk
        batch, joints = p.shape[:2]
        if ctx.ops is not None:
            empty = torch.empty(0, dtype=torch.float64)
            g_t = empty if g_transforms is None else g_transforms.detach().cpu().double().contiguous()
            g_q = empty if g_quats is None else g_quats.detach().cpu().double().contiguous()
            saved = [torch.from_numpy(a) for a in (p, rh, rest)]
            matrices = [torch.from_numpy(a) for a in (big_inv, transforms, quats, local, world, bone, root)]
            parent_rows = torch.as_tensor(parents, dtype=torch.long)
            g_poses, g_rh, g_th = (
                t.numpy() for t in ctx.ops.kin_bones_bwd(*saved, parent_rows, *matrices, g_t, g_q)
            )
            return _bones_grads(ctx, g_transforms, g_quats, g_poses, g_rh, g_th)
        G = np.zeros((batch, joints, 4, 4)) if g_transforms is None else as_float64(g_transforms).copy()
        G[..., 3, :] = 0.0  # the constant bottom row
        if g_quats is not None:  # dL/dq as a gradient of the rotation (module docstring)
            g = as_float64(g_quats)
            qw, qv, gw, gv = quats[..., :1], quats[..., 1:], g[..., :1], g[..., 1:]
            h = -gw * qv + qw * gv + _cross(qv, gv)
            G[..., :3, :3] += _skew(h / 4.0) @ transforms[..., :3, :3]
        # T = root A B^-1
        g_root = (G @ np.swapaxes(bone @ big_inv, -1, -2)).sum(axis=1)
        g_bone = np.swapaxes(root, -1, -2)[:, None] @ G @ np.swapaxes(big_inv, -1, -2)
        # A = W C with C = [I, -rest; 0, 1]: dW = dA C^T, i.e. dW[:, k] -= dA[:, 3] rest_k (k < 3)
        g_world = g_bone.copy()
        g_world[..., :, :3] -= g_bone[..., :, 3:] * rest[:, None, :]
        # W_j = W_parent local_j, back from the leaves
        g_local = np.empty_like(g_world)
        world_t, local_t = np.swapaxes(world, -1, -2), np.swapaxes(local, -1, -2)
        for j in range(joints - 1, 0, -1):
            parent = parents[j]
            g_local[:, j] = world_t[:, parent] @ g_world[:, j]
            g_world[:, parent] += g_world[:, j] @ local_t[:, j]
        g_local[:, 0] = g_world[:, 0]
        g_poses = _left_jacobian_t_times(p, _rotation_grad(g_local[..., :3, :3], local[..., :3, :3]))
        g_rh = _left_jacobian_t_times(rh, _rotation_grad(g_root[:, :3, :3], root[:, :3, :3]))
        g_th = g_root[:, :3, 3]
        return _bones_grads(ctx, g_transforms, g_quats, g_poses, g_rh, g_th)


def _bones_grads(ctx, g_transforms, g_quats, g_poses, g_rh, g_th):
    """_Bones.backward's return: the float64 gradients in the inputs' shapes, dtype and device."""
    poses_shape, rh_shape, th_shape, dtype = ctx.shapes
    need = ctx.needs_input_grad
    device = g_quats.device if g_quats is not None else g_transforms.device

    def out(a, shape, wanted):
        return torch.as_tensor(a, device=device).to(dtype).reshape(shape) if wanted else None

    return (
        out(g_poses, poses_shape, need[0]),
        out(g_rh, rh_shape, need[1]),
        out(g_th, th_shape, need[2]),
        None,
    )


class _PoseKey(torch.autograd.Function):
    @staticmethod
    def forward(ctx, axis_angles):
        p = as_float64(axis_angles)
        ops = _kernel_ops()
        if ops is not None:
            p = np.ascontiguousarray(p)
            rotations = ops.kin_rodrigues_fwd(torch.from_numpy(p)).numpy().reshape(p.shape + (3,))
        else:
            rotations = rodrigues(p)
        ctx.saved = (p, rotations, axis_angles.shape, axis_angles.dtype, ops)
        return torch.as_tensor(rotations, device=axis_angles.device).to(axis_angles.dtype)

    @staticmethod
    def backward(ctx, grad):
        p, rotations, shape, dtype, ops = ctx.saved
        if ops is not None:
            g64 = torch.from_numpy(np.ascontiguousarray(as_float64(grad)))
            g = ops.kin_rodrigues_bwd(torch.from_numpy(p), torch.from_numpy(rotations), g64).numpy()
        else:
            g = _left_jacobian_t_times(p, _rotation_grad(as_float64(grad), rotations))
        return torch.as_tensor(g, device=grad.device).to(dtype).reshape(shape)


def rotation_matrices(axis_angles: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) ``lbs.axis_angle_to_matrix(axis_angles)`` (the colour MLP's pose code with a
    gradient: 23 joints a step) in float64 numpy with its backward written out (the chain rule of
    the bones' rotations above): one autograd node where Rodrigues' formula is ~20 torch ops."""
    return _PoseKey.apply(axis_angles)


def bones(skeleton, poses: torch.Tensor, Rh: torch.Tensor, Th: torch.Tensor):
    """(transforms (B, 24, 4, 4), quats (B, 24, 4)) of ``Skeleton.bones``, differentiable with respect
    to ``poses``, ``Rh`` and ``Th`` through the hand-written backward."""
    return _Bones.apply(poses, Rh, Th, skeleton)
