"""The loss of one training step, term by term, and the adaptive weighting that balances them.

Terms (each reported by name in StepResult.losses and on trainer/metrics):

- ``l1``, ``ssim``: photometric, ``(1 - w) L1 + w (1 - SSIM)`` on the rendered crop (3DGS).
  SSIM: 11x11 Gaussian window (sigma 1.5) over the valid region. Float32 CPU images go to the
  C++ kernel with its analytic backward (``stg_node.splat.image_ops.ssim``); everything else
  (CUDA, float64, no compiler) to ``ssim_torch``, a depthwise separable convolution, which is
  also the kernel's test oracle. Speeds: tools/bench_avatar.py (the ssim section), docs/AVATAR.md.
- ``mask``: ``|alpha - mask|``, so the silhouette matches and nothing grows into the background.
- ``flow``: the 2D motion of the Gaussians between this frame and the next (each Gaussian's
  projected displacement, alpha-blended like a colour) against the DIS optical flow, Charbonnier,
  over pixels where the flow passed the forward-backward check and the person is opaque.
- ``temporal``: non-rigid offsets and temporal opacities agree between consecutive frames
  (offset change in cm plus opacity change), so nothing jitters or pops between frames.
- sparsity of the motion coefficients is not a loss term but a proximal L1 step after each
  update (optim.TableOptimizer.soft_threshold), which yields exact zeros; ``motion_smooth``
  (higher-order coefficients cost more: the motion stays smooth), ``scale``,
  ``opacity``, ``skin``, ``pose``: regularisers.

**Adaptive weighting.** Auxiliary terms ramp in linearly over ``warmup_iters`` (the geometry
must roughly fit before flow can be matched), and each auxiliary term's weighted value is
capped, in running average, at ``AUX_SHARE_MAX`` of the photometric loss: a burst of fast
motion (large flow residuals) or an early transient cannot dominate the image loss, while the
configured weights hold in the normal regime. Weights actually applied are reported.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from stg_node.avatar.config import LossConfig
from stg_node.splat import image_ops
from stg_node.splat.build import load_kernels
from stg_node.splat.image_ops import SSIM_C1, SSIM_C2

AUX_SHARE_MAX = 0.5
EMA_DECAY = 0.98
CHARBONNIER_EPS = 0.5  # px


_KERNELS: dict = {}


def _gaussian_taps(dtype, device) -> torch.Tensor:
    key = (dtype, device)
    if key not in _KERNELS:
        _KERNELS[key] = torch.tensor(image_ops.gaussian_taps(), dtype=dtype, device=device)
    return _KERNELS[key]


def ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of ``(H, W, C)`` images in [0, 1]: 11x11 Gaussian window (sigma 1.5), valid region,
    population statistics (3DGS's and torchmetrics' definition). The C++ kernel where it applies
    (float32 CPU tensors, see image_ops.ssim_kernel_applies), else ``ssim_torch``."""
    if image_ops.ssim_kernel_applies(a, b):
        return image_ops.ssim(a, b)
    return ssim_torch(a, b)


def ssim_torch(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``ssim`` in torch (depthwise separable convolutions, autograd): any device and dtype."""
    c = a.shape[2]
    x = torch.cat([a, b, a * a, b * b, a * b], dim=2).permute(2, 0, 1)[None]  # (1, 5C, H, W)
    n = x.shape[1]
    k = _gaussian_taps(a.dtype, a.device)
    y = F.conv2d(x, k.view(1, 1, 1, 11).expand(n, 1, 1, 11), groups=n)
    y = F.conv2d(y, k.view(1, 1, 11, 1).expand(n, 1, 11, 1), groups=n)[0]
    mu_a, mu_b, aa, bb, ab = y.split(c, dim=0)
    var_a = aa - mu_a * mu_a
    var_b = bb - mu_b * mu_b
    cov = ab - mu_a * mu_b
    num = (2 * mu_a * mu_b + SSIM_C1) * (2 * cov + SSIM_C2)
    den = (mu_a * mu_a + mu_b * mu_b + SSIM_C1) * (var_a + var_b + SSIM_C2)
    return (num / den).mean()


def photometric(render: torch.Tensor, target: torch.Tensor, ssim_weight: float) -> tuple[torch.Tensor, ...]:
    """``(l1, 1 - ssim)`` for ``(H, W, 3)`` images in [0, 1] (at least 11 px each way for SSIM).
    Both from one C++ kernel pass each way where it applies (image_ops.l1_ssim), else torch."""
    if ssim_weight <= 0 or min(render.shape[0], render.shape[1]) < 11:
        return (render - target).abs().mean(), render.new_zeros(())
    if image_ops.ssim_kernel_applies(render, target):
        l1, value = image_ops.l1_ssim(render, target)
        return l1, 1.0 - value
    return (render - target).abs().mean(), 1.0 - ssim_torch(render, target)


class _MeanSquare(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        flat = x.detach().reshape(-1)
        return torch.dot(flat, flat) / flat.numel()

    @staticmethod
    def backward(ctx, grad):
        (x,) = ctx.saved_tensors
        return x * (2.0 * grad / x.numel())


def mean_square(x: torch.Tensor) -> torch.Tensor:
    """``x.pow(2).mean()`` in one pass each way (a dot product; the backward one scaled copy, where
    autograd through pow takes three passes): the regularisers of whole table columns."""
    if x.numel() == 0:
        return x.pow(2).mean()
    return _MeanSquare.apply(x)


class _MeanAbsDifference(torch.autograd.Function):
    @staticmethod
    def forward(ctx, a, b):
        difference = a.detach() - b
        ctx.save_for_backward(difference)
        return difference.abs().mean()

    @staticmethod
    def backward(ctx, grad):
        (difference,) = ctx.saved_tensors
        return difference.sign().mul_(grad / difference.numel()), None


def mean_abs_difference(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``(a - b).abs().mean()`` with ``b`` a constant, as one autograd node (the mask term: where
    autograd keeps three nodes and a temporary each way); the same values and gradient."""
    if b.requires_grad or a.shape != b.shape or a.numel() == 0:
        return (a - b).abs().mean()
    return _MeanAbsDifference.apply(a, b)


FLOW_ALPHA_MIN = 0.5  # the flow term counts pixels at least this opaque


class _FlowLoss(torch.autograd.Function):
    """``flow_loss`` by the C++ kernel (csrc/image_filter.cpp): one pass forward, one backward."""

    @staticmethod
    def forward(ctx, rendered, alpha, flow, valid):
        ops = load_kernels().ops
        r, a = _f32(rendered), _f32(alpha)
        o, v = _f32(flow), valid.contiguous()
        total, count, _, _ = ops.charbonnier_flow(r, a, o, v, FLOW_ALPHA_MIN, CHARBONNIER_EPS, 1.0, False)
        count = int(count)
        ctx.save_for_backward(r, a, o, v)
        ctx.count = count
        if count == 0:
            return rendered.new_zeros(())
        return (total / count - CHARBONNIER_EPS).to(rendered.dtype)

    @staticmethod
    def backward(ctx, grad):
        if ctx.count == 0:
            return None, None, None, None
        r, a, o, v = ctx.saved_tensors
        scale = float(grad) / ctx.count
        _, _, g_r, g_a = load_kernels().ops.charbonnier_flow(
            r, a, o, v, FLOW_ALPHA_MIN, CHARBONNIER_EPS, scale, True
        )
        return g_r, g_a, None, None


def _f32(t: torch.Tensor) -> torch.Tensor:
    return t.detach().to(torch.float32).contiguous()


def flow_loss(rendered: torch.Tensor, alpha: torch.Tensor, flow: torch.Tensor, valid: torch.Tensor):
    """Charbonnier distance (px) between rendered (H, W, 2) and observed flow where ``valid`` (H, W)
    and ``alpha`` (H, W, 1) > 0.5. The C++ kernel for float32 CPU tensors (a gradient for the
    rendered flow and alpha only), else ``flow_loss_torch``."""
    if (
        all(t.device.type == "cpu" and t.dtype == torch.float32 for t in (rendered, alpha, flow))
        and valid.dtype == torch.bool
        and not flow.requires_grad
        and image_ops.kernels_available()
    ):
        return _FlowLoss.apply(rendered, alpha, flow, valid)
    return flow_loss_torch(rendered, alpha, flow, valid)


def flow_loss_torch(rendered: torch.Tensor, alpha: torch.Tensor, flow: torch.Tensor, valid: torch.Tensor):
    """``flow_loss`` in torch (autograd): any device and dtype, and the kernel's test oracle."""
    use = valid & (alpha[..., 0].detach() > FLOW_ALPHA_MIN)
    count = int(use.sum())
    if count == 0:
        return rendered.new_zeros(())
    # Dense over the image, the unused pixels weighted out (their target zeroed, so a NaN where the
    # flow is invalid cannot reach a gradient): no boolean gathers forward or scatters backward.
    observed = torch.where(use[..., None], flow, 0.0)
    diff = rendered / alpha.clamp_min(FLOW_ALPHA_MIN) - observed
    distance = (diff.pow(2).sum(-1) + CHARBONNIER_EPS**2).sqrt()
    return torch.where(use, distance, 0.0).sum() / count - CHARBONNIER_EPS


@dataclass
class AdaptiveWeights:
    """Ramp-in and share cap of the auxiliary terms (see module docstring)."""

    config: LossConfig
    ema: dict[str, float] = field(default_factory=dict)

    def factor(self, iteration: int) -> float:
        warm = self.config.warmup_iters
        return 1.0 if warm <= 0 else min(1.0, iteration / warm)

    def combine(self, terms: dict[str, torch.Tensor], weights: dict[str, float], iteration: int):
        """Total loss and the weights actually applied."""
        photo = terms["photo"]
        self._update("photo", float(photo.detach()))
        total = photo
        applied = {}
        ramp = self.factor(iteration) if self.config.adaptive else 1.0
        for name, value in terms.items():
            if name == "photo":
                continue
            w = weights.get(name, 0.0)
            if w <= 0:
                continue
            if name in ("flow", "temporal") and self.config.adaptive:
                w *= ramp
                mag = self._update(name, float(value.detach()))
                if mag * w > AUX_SHARE_MAX * self.ema["photo"] and mag > 0:
                    w = AUX_SHARE_MAX * self.ema["photo"] / mag
            applied[name] = w
            total = total + w * value
        return total, applied

    def _update(self, name: str, value: float) -> float:
        if not (value == value) or value in (float("inf"), float("-inf")):
            return self.ema.get(name, 0.0)
        prev = self.ema.get(name)
        self.ema[name] = value if prev is None else EMA_DECAY * prev + (1 - EMA_DECAY) * value
        return self.ema[name]
