"""An edge-length loss over a graph of points on the CPU, with its analytic backward (C++ kernel,
csrc/edge_loss.cpp): the as-isometric-as-possible term of ``stg_node.avatar.isometry``.

``edge_length_loss(x, c, a, b)`` is the mean over edges ``(a_e, b_e)`` of
``| |x_a - x_b| - |c_a - c_b| |``: how far the posed distances ``x`` of neighbouring points drift
from their canonical ones ``c``. Autograd over the same maths is a chain of gathers, two norms,
slices and index-adds over (E, 6) tensors (~5 ms forward and backward for 96k edges at 20k
Gaussians); the kernel makes one pass over the edges each way (the forward keeps the lengths, so
the backward gathers no point twice) and scatters the gradients into
both ends in edge order (the same result every run). ``edge_length_loss_torch`` is the torch
implementation: any device and dtype, and the kernel's test oracle (tests/splat/test_edge_ops.py).

Differentiable with respect to ``x`` and ``c``. Where a length is 0 its gradient is 0 and where
the two lengths are equal the residual's is (torch's conventions for norm and abs).
"""

from __future__ import annotations

import torch

from .build import kernels_take, load_kernels


def edge_length_loss_torch(
    x: torch.Tensor, c: torch.Tensor, a: torch.Tensor, b: torch.Tensor
) -> torch.Tensor:
    """``edge_length_loss`` in torch (autograd): the reference, for any device and dtype."""
    both = torch.cat([x, c.to(x.dtype)], dim=1)  # one gather per end of every edge
    d = both.index_select(0, a) - both.index_select(0, b)
    return (d[:, :3].norm(dim=1) - d[:, 3:].norm(dim=1)).abs().mean()


def edge_kernel_applies(x: torch.Tensor, c: torch.Tensor) -> bool:
    """Whether the kernel takes this pair: float32 CPU tensors, and the kernels build here."""
    return kernels_take(x, c)


class _EdgeLength(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, c, a, b):
        x32, c32 = x.detach().contiguous(), c.detach().contiguous()
        a64, b64 = a.to(torch.int64).contiguous(), b.to(torch.int64).contiguous()
        keep = any(ctx.needs_input_grad[:2])  # the lengths, for the backward: no second gather
        value, lengths = load_kernels().ops.edge_length_fwd(x32, c32, a64, b64, keep)
        ctx.save_for_backward(x32, c32, a64, b64, lengths)
        return value.to(x.dtype)

    @staticmethod
    def backward(ctx, grad):
        x32, c32, a64, b64, lengths = ctx.saved_tensors
        want_x, want_c = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        gx, gc = load_kernels().ops.edge_length_bwd(x32, c32, a64, b64, lengths, float(grad), want_x, want_c)
        return (gx if want_x else None), (gc if want_c else None), None, None


def edge_length_loss(x: torch.Tensor, c: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean over the edges ``(a[e], b[e])`` of ``| |x_a - x_b| - |c_a - c_b| |`` (module docstring):
    ``x`` and ``c`` (M, 3) points, ``a`` and ``b`` (E,) row indices. The C++ kernel for float32 CPU
    tensors, else the torch reference; 0 without edges."""
    if x.dim() != 2 or x.shape[1] != 3 or c.shape != x.shape:
        raise ValueError(
            f"edge_length_loss takes two (M, 3) point sets, got {tuple(x.shape)} and {tuple(c.shape)}"
        )
    if a.shape != b.shape or a.dim() != 1:
        raise ValueError(
            f"edge ends must be two (E,) index tensors, got {tuple(a.shape)} and {tuple(b.shape)}"
        )
    if a.numel() == 0:
        return x.new_zeros(()) + 0.0 * c.sum()
    if edge_kernel_applies(x, c):
        return _EdgeLength.apply(x, c, a, b)
    return edge_length_loss_torch(x, c, a, b)
