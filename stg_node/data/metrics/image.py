"""PSNR and SSIM on RGB images in [0, 1] (uint8 inputs are divided by 255).

SSIM follows Wang et al. (2004) the way scikit-image computes it with ``gaussian_weights=True,
sigma=1.5, use_sample_covariance=False, data_range=1``: an 11x11 Gaussian window (radius
``int(3.5 * 1.5 + 0.5) = 5``), per-channel SSIM maps averaged over the image minus a 5-pixel
border, then over channels. The border crop means no padding rule is involved, so a valid
convolution reproduces scikit-image to float64 precision (tested).

``window="uniform7"`` reproduces scikit-image's *defaults* instead (7x7 box window, sample
covariance), which is what 3DGS-Avatar's ZJU-MoCap evaluator calls (``compute_ssim(pred, gt,
channel_axis=0)``); see docs/METRICS.md.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

SSIM_WINDOWS = ("gaussian", "uniform7")
K1, K2 = 0.01, 0.03


def to_tensor(image) -> torch.Tensor:
    """(H, W, C) or (H, W) array/tensor -> float64 tensor (C, H, W) in [0, 1]."""
    if isinstance(image, torch.Tensor):
        t = image.detach().to(torch.float64).cpu()
        is_uint8 = image.dtype == torch.uint8
    else:
        array = np.asarray(image)
        is_uint8 = array.dtype == np.uint8
        t = torch.from_numpy(array.astype(np.float64))
    if is_uint8:
        t = t / 255.0
    if t.ndim == 2:
        t = t[None]
    elif t.ndim == 3:
        t = t.permute(2, 0, 1)
    else:
        raise ValueError(f"expected an (H, W[, C]) image, got shape {tuple(t.shape)}")
    return t.contiguous()


def _check_pair(a: torch.Tensor, b: torch.Tensor) -> None:
    if a.shape != b.shape:
        raise ValueError(f"images differ in shape: {tuple(a.shape)} vs {tuple(b.shape)}")


def psnr(pred, target, mask=None, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB; with ``mask`` (H, W), the MSE is over masked pixels only.

    Identical images give ``inf``.
    """
    a, b = to_tensor(pred), to_tensor(target)
    _check_pair(a, b)
    sq = (a - b) ** 2
    if mask is not None:
        m = torch.from_numpy(np.asarray(mask) > 0) if not isinstance(mask, torch.Tensor) else mask.cpu() > 0
        if m.shape != a.shape[1:]:
            raise ValueError(f"mask shape {tuple(m.shape)} does not match image {tuple(a.shape[1:])}")
        if not m.any():
            raise ValueError("mask is empty: PSNR over no pixels is undefined")
        sq = sq[:, m]
    mse = float(sq.mean())
    return math.inf if mse == 0 else 10.0 * math.log10(data_range**2 / mse)


def _gaussian_kernel(sigma: float = 1.5, truncate: float = 3.5) -> torch.Tensor:
    radius = int(truncate * sigma + 0.5)
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    return k / k.sum()


def ssim_map(pred, target, *, window: str = "gaussian", data_range: float = 1.0) -> torch.Tensor:
    """Per-channel SSIM map (C, H - 2r, W - 2r) over the valid region (r = window radius)."""
    if window not in SSIM_WINDOWS:
        raise ValueError(f"window must be one of {SSIM_WINDOWS}, got {window!r}")
    a, b = to_tensor(pred), to_tensor(target)
    _check_pair(a, b)
    if window == "gaussian":
        k1d = _gaussian_kernel()
        cov_norm = 1.0
    else:
        k1d = torch.full((7,), 1.0 / 7.0, dtype=torch.float64)
        n = 49
        cov_norm = n / (n - 1)  # sample covariance, scikit-image's default
    size = k1d.numel()
    if min(a.shape[1:]) < size:
        raise ValueError(f"image {tuple(a.shape[1:])} is smaller than the {size}x{size} SSIM window")
    channels = a.shape[0]
    kx = k1d.view(1, 1, 1, size).repeat(channels, 1, 1, 1)
    ky = k1d.view(1, 1, size, 1).repeat(channels, 1, 1, 1)

    def blur(x: torch.Tensor) -> torch.Tensor:
        return F.conv2d(F.conv2d(x[None], kx, groups=channels), ky, groups=channels)[0]

    mu_a, mu_b = blur(a), blur(b)
    var_a = cov_norm * (blur(a * a) - mu_a * mu_a)
    var_b = cov_norm * (blur(b * b) - mu_b * mu_b)
    cov = cov_norm * (blur(a * b) - mu_a * mu_b)
    c1, c2 = (K1 * data_range) ** 2, (K2 * data_range) ** 2
    return ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))


def ssim(pred, target, mask=None, *, window: str = "gaussian", data_range: float = 1.0) -> float:
    """Mean SSIM; with ``mask`` (H, W), the mean is over masked pixels of the valid region."""
    smap = ssim_map(pred, target, window=window, data_range=data_range)
    if mask is None:
        return float(smap.mean())
    m = torch.from_numpy(np.asarray(mask) > 0) if not isinstance(mask, torch.Tensor) else mask.cpu() > 0
    full = to_tensor(pred).shape[1:]
    if m.shape != full:
        raise ValueError(f"mask shape {tuple(m.shape)} does not match image {tuple(full)}")
    r = (full[0] - smap.shape[1]) // 2
    m = m[r : full[0] - r, r : full[1] - r]
    if not m.any():
        raise ValueError("mask has no pixel inside the SSIM valid region")
    return float(smap[:, m].mean())
