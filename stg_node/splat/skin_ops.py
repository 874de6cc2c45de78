"""Fused linear blend skinning of Gaussians on the CPU, differentiable (C++ kernel, csrc/skinning.cpp).

``skin(means, skin_weights, bone_transforms, bone_quats, ...)`` carries N canonical points by B
bones in one pass per point: the effective weights (the body's, corrected in log space by a
learned ``skin_delta``: ``w = (s + eps) exp(d) / sum``), the blended transform and the blended
rotation quaternion, the world centre, the product with each point's own rotation and, given a
camera centre, the viewing direction expressed in each point's canonical frame. Autograd's graph
over the same maths is a chain of a dozen ops over (N, B) and (N, 4, 4) tensors; the kernel's
backward is the chain rule written out per point, with the bones' gradients summed in per-thread
buffers. The torch reference it is tested against is ``stg_node.avatar.rigid`` (``blend_weights``,
``skin``) with the quaternion helpers of ``stg_node.avatar.model``.

``next_bone_transforms`` skins a second frame's centres in the same pass (the flow loss's next
frame): the weights, a point's costliest part, are computed once, and the backward pass sums both
frames' gradients of the weights before the correction's chain rule. Its torch reference is two
calls of ``stg_node.avatar.rigid.skin``.

Differentiable with respect to ``means``, ``skin_delta``, ``bone_transforms``, ``bone_quats`` and
``local_quats``; not ``skin_weights`` (fixed columns; ``skin_kernel_applies`` says False when they
require a gradient) and not the view directions. Float32 CPU tensors only.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .build import kernels_take, load_kernels

BONE_STRIDE = 16  # floats per bone handed to the kernel: [R | t] rows (12), then the quaternion (4)


@dataclass
class SkinnedPoints:
    """What :func:`skin` returns."""

    means: torch.Tensor  # (N, 3) world centres
    quats: torch.Tensor | None  # (N, 4) unit wxyz: blended bone rotation x local rotation
    view_dirs: torch.Tensor | None  # (N, 3) unit viewing directions in each point's canonical frame
    blend_norm2: torch.Tensor | None = None  # (N,) squared norm of the blended bone quaternion
    next_means: torch.Tensor | None = None  # (N, 3) world centres under the second frame's bones


def _empty() -> torch.Tensor:
    return torch.empty(0)


def _f32(t: torch.Tensor) -> torch.Tensor:
    return t.detach().to(torch.float32).contiguous()


def skin_kernel_applies(*tensors: torch.Tensor | None) -> bool:
    """Whether :func:`skin` takes these inputs: float32 CPU tensors (None entries are ignored) and
    the kernels build here. Raises nothing; the build's failure is remembered by build.py."""
    return kernels_take(*tensors)


class _Skin(torch.autograd.Function):
    @staticmethod
    def forward(
        ctx,
        means,
        skin_weights,
        skin_delta,
        bones,
        local_quats,
        camera,
        rotations,
        weight_eps,
        quat_eps,
        grad,
        blend_norms,
        next_means,
        next_bones,
    ):
        ops = load_kernels().ops
        m, sw, bo = _f32(means), _f32(skin_weights), _f32(bones)
        delta = _f32(skin_delta) if skin_delta is not None else _empty()
        local = _f32(local_quats) if local_quats is not None else _empty()
        cam = _f32(camera) if camera is not None else _empty()
        two = next_bones is not None
        m2 = _f32(next_means) if two else _empty()
        bo2 = _f32(next_bones) if two else _empty()
        world, quats, view, weights, norms, world2, blends = ops.skin_fwd(
            m, sw, delta, bo, local, cam, rotations, weight_eps, quat_eps, grad, blend_norms, m2, bo2,
            torch.get_num_threads(),
        )  # fmt: skip
        ctx.mark_non_differentiable(view, norms)
        if grad:
            ctx.save_for_backward(m, weights, bo, local, m2, bo2, blends)
        ctx.args = (skin_delta is not None, rotations, quat_eps)
        return world, quats, view, norms, world2

    @staticmethod
    def backward(ctx, g_world, g_quats, _g_view, _g_norms, g_world2):
        m, weights, bo, local, m2, bo2, blends = ctx.saved_tensors
        has_delta, rotations, quat_eps = ctx.args
        two = bo2.numel() > 0
        ops = load_kernels().ops
        g_world = torch.zeros_like(m) if g_world is None else _f32(g_world)
        if rotations:
            g_quats = torch.zeros(m.shape[0], 4) if g_quats is None else _f32(g_quats)
        else:
            g_quats = _empty()
        if two:
            g_world2 = torch.zeros_like(m2) if g_world2 is None else _f32(g_world2)
        else:
            g_world2 = _empty()
        g_means, g_delta, g_bones, g_local, g_means2, g_bones2 = ops.skin_bwd(
            m, weights, has_delta, bo, local, rotations, quat_eps, g_world, g_quats, m2, bo2, g_world2,
            blends, ctx.needs_input_grad[3], ctx.needs_input_grad[12], torch.get_num_threads(),
        )  # fmt: skip
        return (
            g_means,
            None,
            g_delta if has_delta else None,
            g_bones,
            g_local if local.numel() else None,
            None,
            None,
            None,
            None,
            None,
            None,
            g_means2 if two else None,
            g_bones2 if two else None,
        )


def _bone_rows(transforms: torch.Tensor, quats: torch.Tensor | None, b: int) -> torch.Tensor:
    """(B, 16) the kernel's bones: each transform's top three rows, then its quaternion (zeros
    where none is given: a second frame's are never read)."""
    rows = transforms.reshape(b, -1, 4)[:, :3, :].reshape(b, 12)
    quats = rows.new_zeros(b, 4) if quats is None else quats.reshape(b, 4)
    return torch.cat([rows, quats], dim=1)


def skin(
    means: torch.Tensor,
    skin_weights: torch.Tensor,
    bone_transforms: torch.Tensor,
    bone_quats: torch.Tensor,
    *,
    weight_eps: float,
    quat_eps: float,
    skin_delta: torch.Tensor | None = None,
    local_quats: torch.Tensor | None = None,
    camera_center: torch.Tensor | None = None,
    rotations: bool = True,
    blend_norms: bool = False,
    next_bone_transforms: torch.Tensor | None = None,
    next_means: torch.Tensor | None = None,
) -> SkinnedPoints:
    """Skin ``means (N, 3)`` with ``skin_weights (N, B)`` by ``bone_transforms (B, 4, 4)`` (or
    (B, 3, 4)) whose rotations are ``bone_quats (B, 4)`` (wxyz, one hemisphere along the chain).

    ``skin_delta (N, B)``: learned log-space correction of the weights (``weight_eps`` is the floor
    added to the body's weights first); ``local_quats (N, 4)``: each point's own rotation
    (normalised here; a norm <= ``quat_eps`` is the identity), applied after the bones';
    ``camera_center (3,)``: also return the viewing directions in the canonical frame.
    ``rotations=False`` returns the centres only (cheaper). ``blend_norms``: also return the squared
    norm of each point's blended bone quaternion (``sum_b w_b q_b``, before it is normalised; needs
    rotations): the joint squeeze, stg_node.avatar.rigid.joint_shrink.
    ``next_bone_transforms`` (like ``bone_transforms``): also skin ``next_means (N, 3)`` (default:
    ``means``) by these bones with the same weights, centres only (``SkinnedPoints.next_means``).
    """
    n = means.shape[0]
    b = skin_weights.shape[1] if skin_weights.dim() == 2 else -1
    if means.dim() != 2 or means.shape[1] != 3 or skin_weights.shape != (n, b) or b < 1:
        raise ValueError(
            f"skin needs means (N, 3) and skin_weights (N, B), got {tuple(means.shape)} and "
            f"{tuple(skin_weights.shape)}"
        )
    if (
        bone_transforms.shape[-2:] not in ((4, 4), (3, 4))
        or bone_transforms.reshape(-1, *bone_transforms.shape[-2:]).shape[0] != b
    ):
        raise ValueError(
            f"bone_transforms must be ({b}, 4, 4) or ({b}, 3, 4), got {tuple(bone_transforms.shape)}"
        )
    if bone_quats.reshape(-1, 4).shape[0] != b:
        raise ValueError(f"bone_quats must be ({b}, 4), got {tuple(bone_quats.shape)}")
    if skin_delta is not None and skin_delta.shape != (n, b):
        raise ValueError(f"skin_delta must be ({n}, {b}), got {tuple(skin_delta.shape)}")
    if local_quats is not None and local_quats.shape != (n, 4):
        raise ValueError(f"local_quats must be ({n}, 4), got {tuple(local_quats.shape)}")
    if not rotations and (local_quats is not None or camera_center is not None or blend_norms):
        raise ValueError("local_quats, camera_center and blend_norms need rotations=True")
    if skin_weights.requires_grad:
        raise ValueError("skin() does not differentiate skin_weights (learn skin_delta instead)")
    next_bones = None
    if next_bone_transforms is not None:
        if (
            next_bone_transforms.shape[-2:] not in ((4, 4), (3, 4))
            or next_bone_transforms.reshape(-1, *next_bone_transforms.shape[-2:]).shape[0] != b
        ):
            raise ValueError(
                f"next_bone_transforms must be ({b}, 4, 4) or ({b}, 3, 4), got "
                f"{tuple(next_bone_transforms.shape)}"
            )
        next_means = means if next_means is None else next_means
        if next_means.shape != (n, 3):
            raise ValueError(f"next_means must be ({n}, 3), got {tuple(next_means.shape)}")
        next_bones = _bone_rows(next_bone_transforms, None, b)
    elif next_means is not None:
        raise ValueError("next_means needs next_bone_transforms")
    bones = _bone_rows(bone_transforms, bone_quats, b)
    camera = None if camera_center is None else camera_center.reshape(3)
    grad = torch.is_grad_enabled() and any(
        t is not None and t.requires_grad
        for t in (means, skin_delta, bones, local_quats, next_means, next_bones)
    )
    world, quats, view, norms, next_world = _Skin.apply(
        means,
        skin_weights,
        skin_delta,
        bones,
        local_quats,
        camera,
        bool(rotations),
        float(weight_eps),
        float(quat_eps),
        grad,
        bool(blend_norms),
        next_means if next_bones is not None else None,
        next_bones,
    )
    return SkinnedPoints(
        world,
        quats if rotations else None,
        view if camera is not None else None,
        norms if blend_norms else None,
        next_world if next_bones is not None else None,
    )


class _Normals(torch.autograd.Function):
    @staticmethod
    def forward(ctx, quats, scales, means, camera):
        ops = load_kernels().ops
        q, sc, m, cam = _f32(quats), _f32(scales), _f32(means), _f32(camera.reshape(3))
        ctx.save_for_backward(q, sc, m, cam)
        return ops.gaussian_normals_fwd(q, sc, m, cam, torch.get_num_threads())

    @staticmethod
    def backward(ctx, g_normals):
        q, sc, m, cam = ctx.saved_tensors
        ops = load_kernels().ops
        g_quats = ops.gaussian_normals_bwd(q, sc, m, cam, _f32(g_normals), torch.get_num_threads())
        return g_quats, None, None, None


def gaussian_normals(
    quats: torch.Tensor, scales: torch.Tensor, means: torch.Tensor, camera_center: torch.Tensor
) -> torch.Tensor:
    """(M, 3) shading normals of posed Gaussians: stg_node.avatar.shading's ``gaussian_normals``
    (its torch reference) in one pass per point instead of a dozen ops over (M, 3) tensors; the
    same operations in the same order (a last bit apart where torch's own kernels fuse a
    multiply-add). Differentiable with respect to ``quats`` only, as the reference (the axis and
    the sign are constants for the gradient)."""
    n = quats.shape[0]
    if quats.shape != (n, 4) or scales.shape != (n, 3) or means.shape != (n, 3) or camera_center.numel() != 3:
        raise ValueError(
            f"gaussian_normals needs quats (M, 4), scales (M, 3), means (M, 3), a camera centre (3,); got "
            f"{tuple(quats.shape)}, {tuple(scales.shape)}, {tuple(means.shape)}, {tuple(camera_center.shape)}"
        )
    return _Normals.apply(quats, scales, means, camera_center)


class _PixelMotion(torch.autograd.Function):
    @staticmethod
    def forward(ctx, points, next_points, viewmat, K):
        ops = load_kernels().ops
        a, b, v, k = _f32(points), _f32(next_points), _f32(viewmat), _f32(K)
        ctx.save_for_backward(a, b, v, k)
        return ops.pixel_motion_fwd(a, b, v, k, torch.get_num_threads())

    @staticmethod
    def backward(ctx, g_motion):
        a, b, v, k = ctx.saved_tensors
        g_a, g_b = load_kernels().ops.pixel_motion_bwd(a, b, v, k, _f32(g_motion), torch.get_num_threads())
        return g_a, g_b, None, None


def pixel_motion(
    points: torch.Tensor, next_points: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor
) -> torch.Tensor:
    """(N, 2) image motion of world ``points`` (N, 3) to ``next_points`` (N, 3) under one pinhole camera
    (``viewmat`` (4, 4) world -> camera, ``K`` (3, 3)): ``project(next_points) - project(points)``
    as stg_node.avatar.model.Camera3.project (its torch reference; depths clamped below at 1e-6) in
    one pass per point, differentiable with respect to both point sets (not the camera)."""
    n = points.shape[0]
    if points.shape != (n, 3) or next_points.shape != (n, 3):
        raise ValueError(
            "pixel_motion needs points and next_points (N, 3), got "
            f"{tuple(points.shape)}, {tuple(next_points.shape)}"
        )
    if viewmat.shape != (4, 4) or K.shape != (3, 3):
        raise ValueError(
            f"pixel_motion needs viewmat (4, 4) and K (3, 3), got {tuple(viewmat.shape)}, {tuple(K.shape)}"
        )
    if viewmat.requires_grad or K.requires_grad:
        raise ValueError("pixel_motion does not differentiate the camera")
    return _PixelMotion.apply(points, next_points, viewmat, K)
