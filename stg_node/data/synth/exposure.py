"""Per-frame exposure and white-balance drift of the training camera, as a phone's auto-exposure makes it.

``stg-synth --exposure-jitter S`` multiplies each training frame of the training camera by a gain
per colour channel, ``g[f, c] = exp(e[f] + w[f, c])``: ``e`` the exposure (log-gain, standard
deviation ``S``) and ``w`` the white balance (per channel, standard deviation ``S / 2``). Both
drift smoothly (white noise low-passed over about ``CORRELATION_S`` seconds, as auto-exposure
settles on a scene over a fraction of a second to a second), and both have zero mean over the
training frames, so the mean colour of the sequence is the subject's true colour: the held-out
cameras (and the held-out poses) are rendered without any jitter, and an avatar that learned the
subject's colour rather than one frame's exposure scores as well as on a steady subject.

Gains act on the rendered 8-bit sRGB values and clip at 255, as a camera's do (a gain in
linear light is the same gain, to the power 1/2.2, in sRGB: still one gain per channel).
"""

from __future__ import annotations

import numpy as np

CORRELATION_S = 0.5
WHITE_BALANCE_RATIO = 0.5  # white balance's standard deviation, relative to exposure's


def jitter_gains(
    num_frames: int, num_train_frames: int, sigma: float, fps: float, rng: np.random.Generator
) -> np.ndarray:
    """(num_frames, 3) per-channel gains of the training camera; 1 outside the training frames."""
    gains = np.ones((num_frames, 3))
    if sigma <= 0 or num_train_frames < 1:
        return gains
    n = num_train_frames
    width = max(1.0, CORRELATION_S * fps)
    kernel = np.exp(-0.5 * (np.arange(-3 * width, 3 * width + 1) / width) ** 2)
    kernel /= np.sqrt((kernel**2).sum())  # unit variance out of unit-variance white noise

    def smooth_noise(columns: int) -> np.ndarray:
        pad = len(kernel) // 2
        noise = rng.standard_normal((n + 2 * pad, columns))
        out = np.stack([np.convolve(noise[:, c], kernel, mode="valid") for c in range(columns)], axis=1)
        out = out[:n] - out[:n].mean(axis=0)
        std = out.std(axis=0)
        return out / np.where(std > 0, std, 1.0)

    log_gain = sigma * smooth_noise(1) + WHITE_BALANCE_RATIO * sigma * smooth_noise(3)
    gains[:n] = np.exp(log_gain - log_gain.mean(axis=0))
    return gains


def apply_gain(image: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """``image`` (H, W, 3) uint8 times the per-channel ``gain`` (3,), rounded and clipped to [0, 255]."""
    scaled = np.asarray(image, np.float64) * np.asarray(gain, np.float64).reshape(1, 1, 3)
    return np.clip(np.rint(scaled), 0, 255).astype(np.uint8)
