"""The distant lights' irradiance (shading.DistantLights) as one autograd node.

``E(n) = (a + max(0, n d^T) c) / mean`` over every rendered Gaussian is five torch ops forward and
as many autograd nodes backward (two matrix products, the clamp's mask, the division's two
branches), and a ``where`` that holds the rows facing away from the camera out of the gradient
(a broadcast select forward and backward, the largest of them): about 1.2 ms a training step at
20k Gaussians, for a light of 2 x 3 numbers. Here the forward keeps what the backward needs and
the backward is written out: the held rows' gradient multiplied by zero, products over the
Gaussians for the normals, reductions over them for the light's few parameters.

The torch composition (:func:`distant_irradiance_reference`) stays the reference:
``kernels.reference()`` / ``STG_AVATAR_KERNELS=torch`` runs it, and tests/test_light_ops.py
compares both in float64, values and gradients.
"""

from __future__ import annotations

import torch

from stg_node.avatar import kernels


def detach_rows(values: torch.Tensor, rows: torch.Tensor | None) -> torch.Tensor:
    """``values`` (M, C) whose ``rows`` (M,) bool pass no gradient (the same values)."""
    return values if rows is None else torch.where(rows[:, None], values.detach(), values)


def distant_irradiance_reference(normals, ambient, colors, directions, mean, away=None) -> torch.Tensor:
    """(M, 3) ``(a + max(0, n d^T) c) / mean`` for normals (M, 3), ambient (3,), colours (K, 3),
    unit directions (K, 3) and the mean irradiance (3,); rows where ``away`` (M,) bool is set pass
    no gradient."""
    return detach_rows((ambient + (normals @ directions.T).clamp_min(0.0) @ colors) / mean, away)


class _DistantIrradiance(torch.autograd.Function):
    @staticmethod
    def forward(ctx, normals, ambient, colors, directions, mean, keep):
        ctx.set_materialize_grads(False)  # no gradient in: none out (as torch's own nodes)
        facing = normals @ directions.T  # (M, K)
        lit = facing.clamp_min(0.0)
        out = (ambient + lit @ colors) / mean
        ctx.save_for_backward(normals, colors, directions, mean, facing, lit, out, keep)
        return out

    @staticmethod
    def backward(ctx, grad):
        if grad is None:
            return None, None, None, None, None, None
        normals, colors, directions, mean, facing, lit, out, keep = ctx.saved_tensors
        need = ctx.needs_input_grad
        if keep is not None:  # (M, 1) 0 on the rows that pass no gradient: a product, not a where
            grad = grad * keep
        g_sum = grad / mean  # dL/d(a + lit c), (M, 3)
        g_normals = g_ambient = g_colors = g_directions = g_mean = None
        if need[4]:
            g_mean = -(grad * out).sum(0) / mean
        if need[1]:
            g_ambient = g_sum.sum(0)
        if need[2]:
            g_colors = lit.T @ g_sum
        if need[0] or need[3]:
            # clamp_min's mask (the gradient passes where facing >= 0, as torch's clamp_min)
            g_facing = (g_sum @ colors.T).mul_(facing >= 0)
            if need[0]:
                g_normals = g_facing @ directions
            if need[3]:
                g_directions = g_facing.T @ normals
        return g_normals, g_ambient, g_colors, g_directions, g_mean, None


def distant_irradiance(normals, ambient, colors, directions, mean, away=None) -> torch.Tensor:
    """:func:`distant_irradiance_reference` as one autograd node (the reference under
    ``kernels.reference()``)."""
    if kernels.mode() == "torch" or normals.dim() != 2:
        return distant_irradiance_reference(normals, ambient, colors, directions, mean, away)
    keep = None if away is None else (~away)[:, None].to(normals.dtype)
    return _DistantIrradiance.apply(normals, ambient, colors, directions, mean, keep)
