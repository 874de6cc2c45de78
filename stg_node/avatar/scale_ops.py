"""The table's scales as training differentiates them, each with its backward written out.

A step takes the capped scales (``exp`` of the log column, every axis raised to at least
``largest / max_ratio``: gaussians.cap_scale_ratio) for the render and each Gaussian's largest
axis for the scale regulariser. As torch ops these are a row reduction over a dimension of 3 (one
of torch's slowest shapes on a CPU: ~0.13 ms at 20k rows), a broadcast ``maximum`` and their
autograd nodes: about 1.2 ms a step forward and backward at 20k Gaussians. Here each is one
autograd node whose row maximum runs over the three columns elementwise.

Where the CPU kernels build, both run in C++ (``csrc/scale_cap.cpp``: one pass over the rows each
way where the elementwise composition below took ~10 torch ops over (N,) columns; the same values
and gradients to the bit, the exponentials still torch's); the composition runs elsewhere (float64,
other devices). The torch compositions (``cap_scale_ratio(log_scales.exp(), r)``,
``log_scales.exp().max(1)``) stay the reference: ``kernels.reference()`` /
``STG_AVATAR_KERNELS=torch`` runs them, and the tests compare both in float64, values and
gradients, ties included (tests/test_scale_ops.py).
"""

from __future__ import annotations

import torch

from stg_node.avatar import kernels
from stg_node.avatar.gaussians import cap_scale_ratio


def _row_max(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(N,) the largest of each row of ``x`` (N, 3) and (N, 3) the one-hot of its column, the first
    on ties (as ``torch.max(x, 1)``), from elementwise ops over the columns (a reduction over a
    dimension of 3, and a scatter into it, cost ~5x as much)."""
    a, b, c = x.unbind(1)
    ab = torch.maximum(a, b)
    largest = torch.maximum(ab, c)
    third = c > ab
    first = (a >= b) & ~third
    one_hot = torch.stack([first, ~(first | third), third], dim=1).to(x.dtype)
    return largest, one_hot


def _row_sum(x: torch.Tensor) -> torch.Tensor:
    """(N,) the sum of each row of ``x`` (N, 3), in the order ``sum(1)`` adds."""
    a, b, c = x.unbind(1)
    return a + b + c


def _ops(use_kernel: bool):
    """The CPU kernels' operators when ``use_kernel`` (the caller checked kernels.use_kernels)."""
    if not use_kernel:
        return None
    from stg_node.splat.build import load_kernels

    return load_kernels().ops


class _CappedScales(torch.autograd.Function):
    @staticmethod
    def forward(ctx, log_scales: torch.Tensor, max_ratio: float, use_kernel: bool = False) -> torch.Tensor:
        ctx.set_materialize_grads(False)  # no gradient in: none out (as torch's own nodes)
        scales = log_scales.exp()
        ctx.max_ratio = max_ratio
        ctx.ops = _ops(use_kernel)
        if ctx.ops is not None:  # csrc/scale_cap.cpp: the composition below in one pass each way
            ctx.save_for_backward(scales)
            return ctx.ops.scale_capped_fwd(scales.contiguous(), max_ratio)
        largest, one_hot = _row_max(scales)
        floor = (largest / max_ratio)[:, None]
        ctx.save_for_backward(scales, floor, one_hot)
        return torch.maximum(scales, floor)

    @staticmethod
    def backward(ctx, grad: torch.Tensor | None):
        if grad is None:
            return None, None, None
        if ctx.ops is not None:
            (scales,) = ctx.saved_tensors
            return ctx.ops.scale_capped_bwd(scales, ctx.max_ratio, grad.contiguous()), None, None
        scales, floor, one_hot = ctx.saved_tensors
        # torch.maximum's split: the axis where it is above the floor, the floor where below, half
        # each on a tie; the floor's share goes to the largest axis through the division.
        own = (scales > floor).to(grad.dtype)
        tie = scales == floor
        if bool(tie.any()):
            own += 0.5 * tie.to(grad.dtype)
        to_axis = grad * own
        to_floor = _row_sum(grad - to_axis) / ctx.max_ratio
        return to_axis.addcmul_(one_hot, to_floor[:, None]).mul_(scales), None, None


class _LargestScale(torch.autograd.Function):
    @staticmethod
    def forward(ctx, log_scales: torch.Tensor, use_kernel: bool = False) -> torch.Tensor:
        ctx.set_materialize_grads(False)  # no gradient in: none out (as torch's own nodes)
        ops = _ops(use_kernel)
        largest_log, one_hot = ops.scale_row_max(log_scales.contiguous()) if ops else _row_max(log_scales)
        largest = largest_log.exp()  # exp is increasing: the same element as the max of exp
        ctx.save_for_backward(largest, one_hot)
        return largest

    @staticmethod
    def backward(ctx, grad: torch.Tensor | None):
        if grad is None:
            return None, None
        largest, one_hot = ctx.saved_tensors
        return one_hot * (grad * largest)[:, None], None


def _reference(*tensors: torch.Tensor) -> bool:
    return kernels.mode() == "torch" or any(t.shape[-1] != 3 or t.dim() != 2 for t in tensors)


def capped_scales(log_scales: torch.Tensor, max_ratio: float) -> torch.Tensor:
    """(N, 3) ``cap_scale_ratio(exp(log_scales), max_ratio)`` as one autograd node."""
    if max_ratio <= 0 or _reference(log_scales):
        return cap_scale_ratio(log_scales.exp(), max_ratio)
    return _CappedScales.apply(log_scales, float(max_ratio), kernels.use_kernels(log_scales))


def largest_scale(log_scales: torch.Tensor) -> torch.Tensor:
    """(N,) each row's largest axis, ``exp(log_scales).max(1).values``, as one autograd node."""
    if _reference(log_scales):
        return log_scales.exp().max(dim=1).values
    return _LargestScale.apply(log_scales, kernels.use_kernels(log_scales))
