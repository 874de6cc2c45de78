"""Shading under learned distant lights on the CPU, differentiable (C++ kernel, csrc/distant_shading.cpp).

``shade(albedo, normals, visible, strength_logit, ambient, colors, directions)`` is, per row,
``albedo * (1 - k + k visible) * (a + sum_l c_l max(0, n . d_l)) / m`` with the light made from its
parameters as ``stg_node.avatar.shading.DistantLights`` makes it (``a = softplus(ambient)``, ``c =
softplus(colors)``, ``d`` the unit ``directions``, ``m = a + sum_l c_l / 4``) and the occlusion
strength ``k = sigmoid(strength_logit)`` (``stg_node.avatar.occlusion``): the avatar's shading
(``Shading.forward``, its torch reference) in one pass per row, forward and backward, and the
light's few parameters' chain rule in the same call, where torch runs a dozen ops over (M, 3)
tensors, as many over the parameters, and their backward nodes. ``away`` (M,) bool marks rows whose
shade passes no gradient to the light or to their normal.

Differentiable with respect to the albedo, the normals and the parameters; not ``visible`` (the
occlusion is computed without a gradient). Float32 CPU tensors only (``kernels_take``).
"""

from __future__ import annotations

import torch

from .build import load_kernels

MAX_LIGHTS = 8  # csrc/distant_shading.cpp's kMaxLights

_NONE = torch.empty(0)
_NO_ROWS = torch.empty(0, dtype=torch.bool)


def _f32(t: torch.Tensor) -> torch.Tensor:
    return t.detach().to(torch.float32).contiguous()


class _Shade(torch.autograd.Function):
    @staticmethod
    def forward(ctx, albedo, normals, visible, away, strength_logit, ambient, colors, directions):
        inputs = [_f32(albedo), _f32(normals), _NONE if visible is None else _f32(visible)]
        params = [
            _NONE if strength_logit is None else _f32(strength_logit),
            *map(_f32, (ambient, colors, directions)),
        ]
        out = load_kernels().ops.shade_fwd(*inputs, *params, torch.get_num_threads())
        ctx.save_for_backward(*inputs, *params)
        ctx.away = _NO_ROWS if away is None else away.contiguous()
        return out

    @staticmethod
    def backward(ctx, g_out):
        need = ctx.needs_input_grad
        grads = load_kernels().ops.shade_bwd(
            *ctx.saved_tensors, ctx.away, _f32(g_out), bool(need[0]), bool(need[1]), torch.get_num_threads()
        )
        g_albedo, g_normals, g_logit, *g_light = grads
        return (
            g_albedo if need[0] else None,
            g_normals if need[1] else None,
            None,
            None,
            g_logit if need[4] else None,
            *(g if need[5 + i] else None for i, g in enumerate(g_light)),
        )


def shade(
    albedo: torch.Tensor,
    normals: torch.Tensor,
    visible: torch.Tensor | None,
    strength_logit: torch.Tensor | None,
    ambient: torch.Tensor,
    colors: torch.Tensor,
    directions: torch.Tensor,
    away: torch.Tensor | None = None,
) -> torch.Tensor:
    """(M, 3) shaded colours of ``albedo`` (M, 3) at unit world ``normals`` (M, 3) under the light
    of ``ambient`` (3,), ``colors`` and ``directions`` (K, 3) (DistantLights' parameters), times the
    occlusion factor of ``visible`` (M,) with the strength ``strength_logit`` (1,) (both None: no
    factor). ``away`` (M,) bool: rows whose shade teaches the light and their normal nothing."""
    m = albedo.shape[0]
    if albedo.shape != (m, 3) or normals.shape != (m, 3):
        raise ValueError(
            f"albedo and normals must be (M, 3), got {tuple(albedo.shape)}, {tuple(normals.shape)}"
        )
    if (visible is None) != (strength_logit is None) or (visible is not None and visible.shape != (m,)):
        shape = None if visible is None else tuple(visible.shape)
        raise ValueError(
            f"visible ({m},) comes with a strength (or neither), got {shape} and {strength_logit}"
        )
    if visible is not None and visible.requires_grad:
        raise ValueError("visible takes no gradient here (the occlusion is computed without one)")
    if away is not None and (away.shape != (m,) or away.dtype != torch.bool):
        raise ValueError(f"away must be a ({m},) bool tensor, got {away.dtype} {tuple(away.shape)}")
    if colors.dim() != 2 or colors.shape[1] != 3 or directions.shape != colors.shape:
        raise ValueError(
            f"colors and directions must be (K, 3), got {tuple(colors.shape)}, {tuple(directions.shape)}"
        )
    if not 1 <= colors.shape[0] <= MAX_LIGHTS:
        raise ValueError(f"the kernel takes 1 to {MAX_LIGHTS} lights, got {colors.shape[0]}")
    return _Shade.apply(albedo, normals, visible, away, strength_logit, ambient, colors, directions)
