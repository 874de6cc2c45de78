"""Image-space kernels that splatting losses need, on the CPU: SSIM with its analytic backward.

``ssim(a, b)`` is the mean SSIM of two ``(H, W, C)`` images in [0, 1] (Wang et al. 2004 with an
11x11 Gaussian window, sigma 1.5, population statistics, averaged over the 'valid' region:
3DGS's and torchmetrics' definition, and scikit-image's ``structural_similarity(...,
gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1)``), computed by the
C++ kernels (csrc/image_filter.cpp, built with the splat kernels by build.py) and differentiable
with respect to ``a`` (the render). The forward pass filters the five statistics maps in one
fused pass and keeps three derivative maps; the backward pass is the transposed filter of those
(``grad_a = T(d_mu) + 2 a T(d_var) + b T(d_cov)``), several times faster than autograd through
depthwise convolutions.

``l1_ssim(a, b)`` returns the mean absolute difference with the SSIM, differentiable together:
the backward pass adds the L1 term's ``sign(a - b) / n`` in the loop that writes the SSIM's
gradient (the photometric loss of a training step, ``stg_node.avatar.losses.photometric``).

``ssim_kernel_applies(a, b)`` says whether the kernel can take a pair (CPU float32 tensors, ``b``
not requiring a gradient, and the kernels build here); callers keep a torch implementation for
everything else (CUDA tensors, no compiler). The window's constants live here, once.
"""

from __future__ import annotations

import logging
import math

import torch

from .build import load_kernels
from .types import BackendUnavailable

log = logging.getLogger(__name__)

SSIM_WINDOW = 11  # taps per axis of the Gaussian window (radius int(3.5 sigma + 0.5) = 5)
SSIM_SIGMA = 1.5  # pixels
SSIM_C1 = 0.01**2  # (K1 L)^2 with L = 1: images in [0, 1]
SSIM_C2 = 0.03**2  # (K2 L)^2


def gaussian_taps() -> list[float]:
    """The normalised 1-D window (float64 values): the separable factor of the 2-D window."""
    raw = [math.exp(-0.5 * ((i - SSIM_WINDOW // 2) / SSIM_SIGMA) ** 2) for i in range(SSIM_WINDOW)]
    total = sum(raw)
    return [v / total for v in raw]


_TAPS = gaussian_taps()
_unavailable_logged = False


def check_ssim_images(a: torch.Tensor, b: torch.Tensor) -> None:
    """Raise ValueError unless ``a`` and ``b`` are same-shaped (H, W, C) images at least the window."""
    if a.dim() != 3 or b.dim() != 3:
        raise ValueError(
            f"SSIM takes (H, W, C) images, got shapes {tuple(a.shape)} and {tuple(b.shape)} "
            "(a single-channel image needs a trailing axis of 1)"
        )
    if a.shape != b.shape:
        raise ValueError(f"SSIM needs images of one shape, got {tuple(a.shape)} and {tuple(b.shape)}")
    if a.shape[0] < SSIM_WINDOW or a.shape[1] < SSIM_WINDOW:
        raise ValueError(
            f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels (its window), "
            f"got {a.shape[0]}x{a.shape[1]}"
        )
    if a.shape[2] < 1:
        raise ValueError("SSIM needs images with at least one channel")


def ssim_kernel_applies(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Whether ``ssim`` can take this pair: float32 CPU tensors, no gradient wanted for ``b``, and
    the C++ kernels available (built on the first call; a failure is logged once)."""
    if a.device.type != "cpu" or b.device.type != "cpu":
        return False
    if a.dtype != torch.float32 or b.dtype != torch.float32 or b.requires_grad:
        return False
    return kernels_available()


def kernels_available() -> bool:
    """Whether the C++ kernels load here (built on the first call; a failure is logged once: the
    image losses fall back to torch)."""
    global _unavailable_logged
    try:
        load_kernels()
    except BackendUnavailable as exc:
        if not _unavailable_logged:
            _unavailable_logged = True
            log.warning("the image losses fall back to torch: the CPU kernels are unavailable (%s)", exc)
        return False
    return True


def _ssim_forward(ctx, a, b, want_grad):
    """The SSIM kernel's forward pass for an autograd Function: (ops, a32, b32, mean SSIM), with
    what the backward needs saved on ``ctx`` when a gradient is wanted."""
    ops = load_kernels().ops
    a32 = a.detach().to(torch.float32).contiguous()
    b32 = b.detach().to(torch.float32).contiguous()
    value, d_mu, d_var, d_cov = ops.ssim_fwd(
        a32, b32, _TAPS, SSIM_C1, SSIM_C2, want_grad, torch.get_num_threads()
    )
    if want_grad:
        ctx.save_for_backward(a32, b32, d_mu, d_var, d_cov)
    return ops, a32, b32, value


class _Ssim(torch.autograd.Function):
    @staticmethod
    def forward(ctx, a, b, want_grad):
        _, _, _, value = _ssim_forward(ctx, a, b, want_grad)
        return value.to(a.dtype)

    @staticmethod
    def backward(ctx, grad):
        a32, b32, d_mu, d_var, d_cov = ctx.saved_tensors
        ops = load_kernels().ops
        grad_a = ops.ssim_bwd(a32, b32, _TAPS, d_mu, d_var, d_cov, float(grad), 0.0, torch.get_num_threads())
        return grad_a, None, None


class _L1Ssim(torch.autograd.Function):
    """(mean |a - b|, mean SSIM) of one pair: one SSIM pass forward, and one backward pass that
    writes the gradient of both (the photometric loss's two terms, ``l1_ssim``)."""

    @staticmethod
    def forward(ctx, a, b, want_grad):
        ops, a32, b32, value = _ssim_forward(ctx, a, b, want_grad)
        l1 = ops.abs_diff_sum(a32, b32) / a32.numel()
        return l1.to(a.dtype), value.to(a.dtype)

    @staticmethod
    def backward(ctx, grad_l1, grad_ssim):
        a32, b32, d_mu, d_var, d_cov = ctx.saved_tensors
        ops = load_kernels().ops
        g_l1 = 0.0 if grad_l1 is None else float(grad_l1) / a32.numel()
        g_ssim = 0.0 if grad_ssim is None else float(grad_ssim)
        grad_a = ops.ssim_bwd(a32, b32, _TAPS, d_mu, d_var, d_cov, g_ssim, g_l1, torch.get_num_threads())
        return grad_a, None, None


def _check_kernel_pair(name: str, a: torch.Tensor, b: torch.Tensor) -> None:
    """The kernels' terms: SSIM's image checks, CPU tensors, and no gradient wanted for ``b``."""
    check_ssim_images(a, b)
    if a.device.type != "cpu" or b.device.type != "cpu":
        raise ValueError(f"image_ops.{name} runs on CPU tensors, got {a.device} and {b.device}")
    if b.requires_grad:
        raise ValueError(
            f"image_ops.{name} differentiates only its first image; b requires a gradient "
            "(detach it, or use a torch implementation)"
        )


def ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of ``(H, W, C)`` CPU images in [0, 1] (module docstring), as a 0-d tensor of
    ``a``'s dtype; differentiable with respect to ``a`` only. Computed in float32."""
    _check_kernel_pair("ssim", a, b)
    # Without a gradient to come (no_grad, or `a` a constant) the derivative maps are not made.
    return _Ssim.apply(a, b, torch.is_grad_enabled() and a.requires_grad)


def l1_ssim(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(mean |a - b|, mean SSIM)`` of ``(H, W, C)`` CPU images (the photometric loss's two terms),
    differentiable with respect to ``a``: one kernel pass each way for both, where the L1 term in
    torch would add four passes over the image (difference, abs, mean, and the sum of the two
    terms' gradients). Computed in float32; the same checks as ``ssim``."""
    _check_kernel_pair("l1_ssim", a, b)
    return _L1Ssim.apply(a, b, torch.is_grad_enabled() and a.requires_grad)
