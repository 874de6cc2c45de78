"""LPIPS v0.1 (Zhang et al., CVPR 2018) in plain torch: AlexNet and VGG16 variants, no torchvision.

The network is the official one: inputs in [-1, 1] shifted and scaled per channel, five ReLU
feature taps (AlexNet relu1..relu5; VGG16 relu1_2, relu2_2, relu3_3, relu4_3, relu5_3), each tap
unit-normalised over channels (``x / (|x| + 1e-10)``), squared difference, a learned 1x1 linear
layer, spatial mean, sum over taps. Weights come from :mod:`.lpips_weights`; without them
:class:`LpipsUnavailable` is raised with the reason, and callers report LPIPS as unavailable.

Images passed here are in [0, 1] (``normalize=True`` in the official package's terms).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from stg_node.data.metrics.lpips_weights import (
    CONVS,
    NETS,
    VGG_CHANNELS,
    LpipsWeightsError,
    load_state,
)

SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
ALEX_POOL_AFTER = {0, 1}  # 3x3/2 max-pool after these convs (before the next)
VGG_TAPS = {1, 3, 6, 9, 12}  # conv indices whose ReLU output is a tap
MIN_SIZE = {"alex": 32, "vgg": 16}


class LpipsUnavailable(RuntimeError):
    """LPIPS cannot be computed here; ``str()`` says why (never a substitute number)."""


class LPIPS(nn.Module):
    """``LPIPS(net)(pred, target)`` -> distance per image, inputs ``(N, 3, H, W)`` in [0, 1]."""

    def __init__(self, net: str = "alex", state: dict | None = None, directory: Path | None = None):
        super().__init__()
        if net not in NETS:
            raise ValueError(f"net must be one of {NETS}, got {net!r}")
        self.net = net
        self.backbone = nn.ModuleList(
            nn.Conv2d(cin, cout, k, stride=s, padding=p) for cin, cout, k, s, p in CONVS[net]
        )
        taps = [64, 192, 384, 256, 256] if net == "alex" else [64, 128, 256, 512, 512]
        self.lin = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in taps)
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1), persistent=False)
        if state is None:
            try:
                state = load_state(net, directory)
            except LpipsWeightsError as exc:
                raise LpipsUnavailable(str(exc)) from exc
        self.load_state_dict({k: torch.from_numpy(v) for k, v in state.items()})
        self.eval().requires_grad_(False)

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        taps = []
        if self.net == "alex":
            for i, conv in enumerate(self.backbone):
                x = F.relu(conv(x))
                taps.append(x)
                if i in ALEX_POOL_AFTER:
                    x = F.max_pool2d(x, 3, 2)
            return taps
        convs = iter(enumerate(self.backbone))
        for item in VGG_CHANNELS:
            if item == "M":
                x = F.max_pool2d(x, 2, 2)
                continue
            i, conv = next(convs)
            x = F.relu(conv(x))
            if i in VGG_TAPS:
                taps.append(x)
        return taps

    def forward(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        if pred.shape != target.shape or pred.ndim != 4 or pred.shape[1] != 3:
            raise ValueError(
                f"expected two (N, 3, H, W) batches, got {tuple(pred.shape)} and {tuple(target.shape)}"
            )
        if min(pred.shape[-2:]) < MIN_SIZE[self.net]:
            raise ValueError(
                f"LPIPS-{self.net} needs images of at least {MIN_SIZE[self.net]} px, got {pred.shape[-2:]}"
            )
        x = torch.cat([pred, target]).to(self.shift.dtype) * 2 - 1
        feats = self.features((x - self.shift) / self.scale)
        total = 0
        for lin, f in zip(self.lin, feats, strict=True):
            f = f / (f.square().sum(dim=1, keepdim=True).sqrt() + 1e-10)
            fa, fb = f.chunk(2)
            total = total + lin((fa - fb).square()).mean(dim=(2, 3))
        return total.view(-1)


@lru_cache(maxsize=4)
def _model(net: str, directory: str | None) -> LPIPS:
    return LPIPS(net, directory=Path(directory) if directory else None)


def get_lpips(net: str = "alex", directory: Path | None = None) -> LPIPS:
    """A shared LPIPS module (weights loaded once per process); LpipsUnavailable if not installed."""
    return _model(net, str(directory) if directory else None)


def lpips_available(net: str = "alex", directory: Path | None = None) -> tuple[bool, str]:
    """(True, '') or (False, reason)."""
    try:
        load_state(net, directory)
    except LpipsWeightsError as exc:
        return False, str(exc)
    return True, ""


def lpips_distance(pred, target, net: str = "alex", directory: Path | None = None) -> float:
    """LPIPS between two (H, W, 3) images in [0, 1] (or uint8)."""
    from stg_node.data.metrics.image import to_tensor

    a, b = to_tensor(pred).float()[None], to_tensor(target).float()[None]
    with torch.no_grad():
        return float(get_lpips(net, directory)(a, b)[0])
