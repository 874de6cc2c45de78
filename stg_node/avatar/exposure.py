"""A per-frame colour correction learnt in training: exposure and white balance that drift between frames.

A phone's auto-exposure and auto-white-balance change every frame a little. Without a model of it,
the avatar's colour chases each frame's exposure and ends as a blurred average that is right for
none of them (and flickers in the Gaussians that see few frames). Here each training frame gets
three learnt log-gains, one per colour channel, and the render is multiplied by them before the
loss: ``rendered x exp(g_frame)``. Exposure is one gain for all channels, white balance one per
channel; in 8-bit sRGB both are still one gain per channel (a gain in linear light is a gain to
the power 1/2.2), so three numbers model both exactly, and a black background stays black.

- **Gauge**: the avatar's colours times ``exp(c)`` and every frame's gain times ``exp(-c)`` render
  the same; a small penalty on ``g`` (``loss.exposure``) picks the solution whose gains are about
  zero on average, i.e. the avatar learns the sequence's mean colour, which is what a steady
  camera would have seen.
- **Only in training**: renders (stg-render, the renderer node, stg-eval) show the avatar's own
  colour; the gains stay in the checkpoint.
- **Sparse updates**: a frame's gains get a gradient only in the steps that draw it (about 15 in a
  fast run of 100 frames). A plain Adam over the whole table would keep moving every row with
  stale momentum in the steps between; this Adam updates the drawn row alone, with its own
  moments and step count (as torch's SparseAdam does for embeddings).
- Starts after ``loss.warmup_iters`` (the avatar's colour must form first, or the gains would
  absorb its early errors).
"""

from __future__ import annotations

import math

import numpy as np
import torch

BETAS = (0.9, 0.999)
EPS = 1e-8
MAX_LOG_GAIN = 1.0  # e^1: far beyond any auto-exposure step; keeps a bad step from running away


class ExposureCorrection:
    """Learnt per-frame log-gains (3 per frame) and their sparse Adam state."""

    def __init__(self, lr: float, weight: float, start_iter: int, device="cpu"):
        self.lr = float(lr)
        self.weight = float(weight)
        self.start_iter = int(start_iter)
        self.device = torch.device(device)
        self.slots: dict[int, int] = {}  # frame index -> row
        self.gains = torch.zeros(0, 3, device=self.device)  # log-gains
        self.exp_avg = torch.zeros(0, 3, device=self.device)
        self.exp_avg_sq = torch.zeros(0, 3, device=self.device)
        self.steps = torch.zeros(0, dtype=torch.int64)
        self._active: tuple[int, torch.Tensor] | None = None  # the row in use this step

    @property
    def enabled(self) -> bool:
        return self.lr > 0

    def add(self, index: int) -> None:
        if index in self.slots:
            return
        self.slots[int(index)] = len(self.slots)
        pad = torch.zeros(1, 3, device=self.device)
        self.gains = torch.cat([self.gains, pad])
        self.exp_avg = torch.cat([self.exp_avg, pad])
        self.exp_avg_sq = torch.cat([self.exp_avg_sq, pad])
        self.steps = torch.cat([self.steps, torch.zeros(1, dtype=torch.int64)])

    def retain(self, frames) -> None:
        """Keep the rows (gains and Adam state) of ``frames`` only: a bounded trainer forgets the
        frames its store no longer holds, so a stream's rows stay as many as its frames."""
        kept = sorted((row, f) for f, row in self.slots.items() if f in frames)
        rows = torch.tensor([row for row, _ in kept], dtype=torch.long)
        self.gains = self.gains[rows.to(self.device)]
        self.exp_avg = self.exp_avg[rows.to(self.device)]
        self.exp_avg_sq = self.exp_avg_sq[rows.to(self.device)]
        self.steps = self.steps[rows]
        self.slots = {f: i for i, (_, f) in enumerate(kept)}

    def apply(self, rgb: torch.Tensor, index: int, iteration: int) -> torch.Tensor:
        """``rgb`` (H, W, 3) times this frame's gains (learnable from ``start_iter`` on)."""
        self._active = None
        if not self.enabled or index not in self.slots:
            return rgb
        row = self.slots[index]
        if iteration < self.start_iter:
            return rgb * self.gains[row].exp()
        g = self.gains[row].clone().requires_grad_(True)
        self._active = (row, g)
        return rgb * g.exp()

    def penalty(self) -> torch.Tensor | None:
        """``weight`` x the squared log-gains of this step's frame (the gauge, module docstring)."""
        if self._active is None or self.weight <= 0:
            return None
        return self._active[1].pow(2).sum()

    def step(self) -> None:
        """One Adam update of this step's row (after ``backward``); nothing when no row was active."""
        if self._active is None:
            return
        row, g = self._active
        self._active = None
        if g.grad is None or not bool(torch.isfinite(g.grad).all()):
            return
        grad = g.grad.detach()
        b1, b2 = BETAS
        self.exp_avg[row] = b1 * self.exp_avg[row] + (1 - b1) * grad
        self.exp_avg_sq[row] = b2 * self.exp_avg_sq[row] + (1 - b2) * grad * grad
        self.steps[row] += 1
        t = int(self.steps[row])
        m_hat = self.exp_avg[row] / (1 - b1**t)
        v_hat = self.exp_avg_sq[row] / (1 - b2**t)
        update = self.lr * m_hat / (v_hat.sqrt() + EPS)
        self.gains[row] = (self.gains[row] - update).clamp(-MAX_LOG_GAIN, MAX_LOG_GAIN)

    def discard(self) -> None:
        """Forget this step's row without updating it (a step skipped for non-finite values)."""
        self._active = None

    def gains_of(self) -> dict[int, np.ndarray]:
        """Frame index -> (3,) learnt gains (linear, not log)."""
        values = self.gains.exp().cpu().numpy()
        return {frame: values[row] for frame, row in self.slots.items()}

    # --- checkpoints ---------------------------------------------------------------------------
    def state_arrays(self) -> dict[str, np.ndarray]:
        if not self.slots:
            return {}
        frames = sorted(self.slots, key=self.slots.get)
        return {
            "frames": np.asarray(frames, np.float32),  # snapshot arrays are float32: exact below 2^24
            "gains": self.gains.cpu().numpy().astype(np.float32),
            "exp_avg": self.exp_avg.cpu().numpy().astype(np.float32),
            "exp_avg_sq": self.exp_avg_sq.cpu().numpy().astype(np.float32),
            "steps": self.steps.numpy().astype(np.float32),
        }

    def load_state_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        if "frames" not in arrays:
            return
        frames = [int(f) for f in np.asarray(arrays["frames"])]
        self.slots = {f: i for i, f in enumerate(frames)}

        def t(name):
            return torch.as_tensor(np.array(arrays[name], np.float32), device=self.device).reshape(-1, 3)

        self.gains, self.exp_avg, self.exp_avg_sq = t("gains"), t("exp_avg"), t("exp_avg_sq")
        self.steps = torch.as_tensor(np.array(arrays["steps"]).round().astype(np.int64))


def log_gain_error(learnt: dict[int, np.ndarray], truth: dict[int, np.ndarray]) -> float:
    """RMS difference of learnt and true log-gains over the frames both know, after removing each
    side's mean (the gauge): how well the correction found the drift (tests, benchmarks)."""
    frames = sorted(set(learnt) & set(truth))
    if not frames:
        return math.nan
    a = np.log(np.stack([learnt[f] for f in frames]))
    b = np.log(np.stack([truth[f] for f in frames]))
    a -= a.mean(axis=0)
    b -= b.mean(axis=0)
    return float(np.sqrt(((a - b) ** 2).mean()))
