"""Colour of each Gaussian: the paper's light MLP, or plain spherical harmonics.

MLP (STG-Avatar): ``c_i(t) = F(gamma(mu_i(t)), f_i, gamma(theta), SH(d_i))`` where mu_i(t) is the
Gaussian's canonical centre plus its spacetime offset, gamma a sin/cos positional encoding,
f_i a learned per-Gaussian feature (the motion/appearance feature f_mot), theta the body pose
(its 23 local joint rotations, linearly encoded to a few features), and SH(d_i) the real SH
basis of the viewing direction expressed in the Gaussian's canonical frame (so view dependence
turns with the body). A sigmoid keeps colours in [0, 1]. About 10-20k weights at the presets'
sizes, far under the paper's 0.8M bound.

SH: 3DGS's per-Gaussian coefficients, ``rgb = max(0, 0.5 + sum_lm c_lm Y_lm(d))``.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from stg_node.avatar import kernels
from stg_node.avatar.config import ModelConfig
from stg_node.splat import mlp_ops
from stg_node.splat.sh import SH_C0 as SH_C0  # read here by export.py and shading.py
from stg_node.splat.sh import sh_basis


def sh_color(coeffs: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """RGB ``(N, 3)`` from SH coefficients ``(N, K, 3)`` using the first ``degree`` bands."""
    k = (degree + 1) ** 2
    basis = sh_basis(degree, dirs)  # (N, k)
    return ((basis[..., None] * coeffs[:, :k]).sum(dim=1) + 0.5).clamp_min(0.0)


def positional_encoding(x: torch.Tensor, freqs: int) -> torch.Tensor:
    """``[x, sin(2^k pi x), cos(2^k pi x)]_{k<freqs}`` for x roughly in [-1, 1]."""
    return x if freqs == 0 else encoded_inputs(x, freqs)


def encoded_inputs(x: torch.Tensor, freqs: int, *rest: torch.Tensor) -> torch.Tensor:
    """``cat([positional_encoding(x, freqs), *rest], -1)``, the same values in one concatenation
    instead of two (the colour MLP's input: a renderer builds it every frame, a training step
    differentiates it: see :class:`_EncodedInputs`)."""
    if freqs == 0:
        return torch.cat([x, *rest], dim=-1)
    scales = (2.0 ** torch.arange(freqs, dtype=x.dtype, device=x.device)) * math.pi
    if torch.is_grad_enabled() and any(t.requires_grad for t in (x, *rest)):
        return _EncodedInputs.apply(x, scales, *rest)
    angles = (x[..., None] * scales).flatten(-2)
    return torch.cat([x, torch.sin(angles), torch.cos(angles), *rest], dim=-1)


class _EncodedInputs(torch.autograd.Function):
    """:func:`encoded_inputs` (the same forward ops, so the same values) with a backward that
    reuses the forward's sines and cosines, where autograd's computes both again on every
    (rows x 3 x freqs) angle, and hands each input its slice of the gradient in a few ops:
    ``dL/dx = g_x + sum_k s_k (g_sin_k cos_k - g_cos_k sin_k)``."""

    @staticmethod
    def forward(ctx, x, scales, *rest):
        angles = (x[..., None] * scales).flatten(-2)
        sin, cos = torch.sin(angles), torch.cos(angles)
        ctx.save_for_backward(sin, cos, scales)
        ctx.widths = [t.shape[-1] for t in rest]
        return torch.cat([x, sin, cos, *rest], dim=-1)

    @staticmethod
    def backward(ctx, grad):
        sin, cos, scales = ctx.saved_tensors
        k = sin.shape[-1]
        d = k // scales.shape[0]
        g_x = None
        if ctx.needs_input_grad[0]:
            g_angles = grad[..., d : d + k] * cos - grad[..., d + k : d + 2 * k] * sin
            # a product with the scales: a sum over the last 4-wide axis is a slow reduction in torch
            g_x = grad[..., :d] + g_angles.unflatten(-1, (d, scales.shape[0])) @ scales
        grads_rest = []
        start = d + 2 * k
        for i, width in enumerate(ctx.widths):
            grads_rest.append(grad[..., start : start + width] if ctx.needs_input_grad[2 + i] else None)
            start += width
        return g_x, None, *grads_rest


class ColorMLP(nn.Module):
    """The light colour MLP; ``bounds`` (2, 3) maps canonical coordinates to [-1, 1] for gamma()."""

    def __init__(self, config: ModelConfig, bounds: torch.Tensor):
        super().__init__()
        self.config = config
        self.register_buffer("bounds", bounds.float().clone())
        self.pose_encoder = nn.Linear(23 * 9, config.pose_dim) if config.pose_dim > 0 else None
        in_dim = 3 * (1 + 2 * config.pos_freqs) + config.feature_dim + config.pose_dim
        in_dim += (config.sh_degree + 1) ** 2
        layers: list[nn.Module] = []
        width = in_dim
        for _ in range(config.mlp_layers):
            layers += [nn.Linear(width, config.mlp_width), nn.ReLU(inplace=True)]
            width = config.mlp_width
        layers.append(nn.Linear(width, 3))
        self.net = nn.Sequential(*layers)
        with torch.no_grad():  # start grey: zero output bias and small last layer
            self.net[-1].weight.mul_(0.1)
            self.net[-1].bias.zero_()
        if self.pose_encoder is not None:
            with torch.no_grad():
                self.pose_encoder.weight.mul_(0.1)

    def forward(
        self,
        canonical_means: torch.Tensor,
        features: torch.Tensor,
        pose_key: torch.Tensor,
        view_dirs: torch.Tensor,
        sh_degree: int,
        rows: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Colours (M, 3) in [0, 1] of the Gaussians at ``rows`` (int64 (M,), distinct; None: every
        row) of ``canonical_means`` (N, 3), ``features`` (N, F) and ``view_dirs`` (N, 3, unit, in the
        canonical frame), under the pose ``pose_key`` (1, 207), with the view's SH bands up to
        ``sh_degree``. The kernel reads the selected rows where they lie (a training step's turn of
        the rows: no gathered copies) and hands their gradients back at their rows."""
        layers = mlp_ops.layers_of(self.net, "sigmoid")
        fused = layers is not None and kernels.use_kernels(canonical_means, features, *self.net.parameters())
        if rows is not None and not fused:
            canonical_means, features, view_dirs = (
                t.index_select(0, rows) for t in (canonical_means, features, view_dirs)
            )
            rows = None
        lo, hi = self.bounds[0], self.bounds[1]
        x = (canonical_means - lo) / (hi - lo).clamp_min(1e-6) * 2.0 - 1.0
        freqs = self.config.pos_freqs
        n = canonical_means.shape[0]
        pose = None if self.pose_encoder is None else self.pose_encoder(pose_key)
        active = min(sh_degree, self.config.sh_degree)
        if fused:
            if pose is not None:  # the same pose code in every row: folded into the first bias
                start = x.shape[1] * (1 + 2 * freqs) + features.shape[1]
                layers = mlp_ops.fold_constant_inputs(layers, slice(start, start + pose.shape[1]), pose[0])
            # the kernel builds gamma(x) and SH(d) itself, block by block (mlp_ops.InputEncoding)
            encoding = mlp_ops.InputEncoding(
                x.shape[1] if freqs > 0 else 0, freqs, view_degree=self.config.sh_degree, view_active=active
            )
            return mlp_ops.mlp([x, features, view_dirs], layers, encoding, rows)
        basis = sh_basis(self.config.sh_degree, view_dirs)
        if active < self.config.sh_degree:  # bands not yet switched on are fed as zeros
            keep = (active + 1) ** 2
            basis = torch.cat([basis[:, :keep], basis.new_zeros(n, basis.shape[1] - keep)], dim=1)
        parts = [positional_encoding(x, freqs), features]
        if pose is not None:
            parts.append(pose.expand(n, -1))
        parts.append(basis)
        return torch.sigmoid(self.net(torch.cat(parts, dim=-1)))

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())
