"""A per-frame colour correction learnt in training: exposure and white balance that drift between frames.

A phone's auto-exposure and auto-white-balance change every frame a little. Without a model of it,
the avatar's colour chases each frame's exposure and ends as a blurred average that is right for
none of them (and, through the colour MLP's pose input, a colour that changes with the pose).
Here each training frame has three log-gains, one per colour channel, and the render is
multiplied by them before the loss: ``rendered x exp(g_frame - mean g)``. Exposure is one gain for
all channels, white balance one per channel; in 8-bit sRGB both are still one gain per channel (a
gain in linear light is a gain to the power 1/2.2), so three numbers model both, and a black
background stays black. An offset or a 3x3 colour matrix per frame would fit more, but from one
crop of one frame it also fits the avatar's own errors (an offset lifts the black background).

- **Solved, not descended**: each time a frame is drawn, its gains move towards the least-squares
  gains of that draw, ``sum(r t) / sum(r r)`` per channel over the pixels where the person is both
  rendered and seen (``r`` the render, ``t`` the image; saturated image pixels left out: a clipped
  pixel says nothing of the gain), by the share ``rate`` (``lr_exposure``; a Gauss-Newton step
  damped so that one draw's estimate against a half-trained avatar does not settle it). A frame is
  drawn a few dozen times in a run, and a gradient step of a usual rate moves a log-gain by about
  the rate per draw: the Adam this replaces (rate 1e-2) ended with a third of the true drift
  (benchmark in docs/BENCHMARKS.md, "Real footage"), and the avatar absorbed the rest, per
  frame, through its pose- and time-dependent colour.
- **Gauge**: the avatar's colours times ``exp(c)`` and every frame's gain times ``exp(-c)`` render
  the same. The applied gains have their mean over the frames removed (per channel), so the
  avatar learns the sequence's mean colour (the geometric mean of its exposures), which is what
  a steady camera at the mean setting would have seen, whatever brightness the avatar has while
  it learns: a render too dark by ``c`` raises every estimate by ``c`` and the mean takes it away.
- **Saturation**: the corrected render is clipped at 1 as the camera clips, so a frame exposed
  brighter does not teach the avatar a darker colour where the image saturated.
- **Where it is on**: footage from cameras that set their own exposure (``stg-train --format
  video``, the trainer node on a live camera; :func:`for_footage`). Off by default for datasets
  filmed at a fixed exposure (ZJU-MoCap, stg-synth, the folder format): there the gains can only
  take what they cannot tell from exposure, a body turning its lit side away, which cost a steady
  synthetic subject 0.27 dB (docs/BENCHMARKS.md, "Real footage"). ``--set lr_exposure=`` decides
  either way.
- **Only in training**: renders (stg-render, the renderer node, stg-eval) show the avatar's own
  colour; the gains stay in the checkpoint.
- Starts after ``exposure_start`` steps (the avatar's colour must form first, or the estimates
  would be ratios against the initial grey), early enough that the avatar has not yet learnt
  each frame's exposure itself.
"""

from __future__ import annotations

import math

import numpy as np
import torch

FOOTAGE_RATE = 0.5  # lr_exposure for footage from cameras that set their own exposure
MAX_LOG_GAIN = 1.0  # e^1: far beyond any auto-exposure step; keeps a bad estimate from running away
SATURATED = 254.5 / 255.0  # an image value at or above this clipped in the camera
MIN_PIXELS = 64  # a draw where fewer pixels show the person (per channel) estimates nothing


class ExposureCorrection:
    """Per-frame log-gains (3 per frame), estimated in closed form from each draw of the frame."""

    def __init__(self, rate: float, start_iter: int, device="cpu"):
        if not 0.0 <= float(rate) <= 1.0:
            raise ValueError(f"lr_exposure must be 0 (off) to 1 (each draw's estimate as is), got {rate}")
        self.rate = float(rate)
        self.start_iter = int(start_iter)
        self.device = torch.device(device)
        self.slots: dict[int, int] = {}  # frame index -> row
        self.gains = torch.zeros(0, 3, device=self.device)  # log-gains, before the gauge's mean
        self.steps = torch.zeros(0, dtype=torch.int64)  # draws that estimated each row

    @property
    def enabled(self) -> bool:
        return self.rate > 0

    def add(self, index: int) -> None:
        if index in self.slots:
            return
        self.slots[int(index)] = len(self.slots)
        self.gains = torch.cat([self.gains, torch.zeros(1, 3, device=self.device)])
        self.steps = torch.cat([self.steps, torch.zeros(1, dtype=torch.int64)])

    def retain(self, frames) -> None:
        """Keep the rows of ``frames`` only: a bounded trainer forgets the frames its store no
        longer holds, so a stream's rows stay as many as its frames."""
        kept = sorted((row, f) for f, row in self.slots.items() if f in frames)
        rows = torch.tensor([row for row, _ in kept], dtype=torch.long)
        self.gains = self.gains[rows.to(self.device)]
        self.steps = self.steps[rows]
        self.slots = {f: i for i, (_, f) in enumerate(kept)}

    def _mean(self) -> torch.Tensor:
        """(3,) mean log-gain of the frames estimated so far (the gauge: module docstring)."""
        seen = self.steps > 0
        if not bool(seen.any()):
            return torch.zeros(3, device=self.device)
        return self.gains[seen.to(self.device)].mean(dim=0)

    def estimate(self, row: int, rgb: torch.Tensor, target: torch.Tensor, region: torch.Tensor) -> None:
        """Move ``row``'s log-gains towards this draw's least-squares gains (module docstring).

        ``rgb`` and ``target`` (H, W, 3) in [0, 1], ``region`` (H, W) bool: the pixels that show the
        person in both."""
        valid = (region[..., None] & (target < SATURATED) & (rgb > 0)).to(rgb.dtype)
        num = (valid * rgb * target).sum(dim=(0, 1))
        den = (valid * rgb * rgb).sum(dim=(0, 1))
        ok = (valid.sum(dim=(0, 1)) >= MIN_PIXELS) & (num > 0) & (den > 0)
        if not bool(ok.all()):  # a channel without evidence keeps its gain (all three move together)
            return
        drawn = (num / den).log().clamp(-MAX_LOG_GAIN, MAX_LOG_GAIN)
        rate = 1.0 if int(self.steps[row]) == 0 else self.rate  # the first estimate replaces the 0
        self.gains[row] = self.gains[row] + rate * (drawn - self.gains[row])
        self.steps[row] += 1

    def apply(
        self,
        rgb: torch.Tensor,
        index: int,
        iteration: int,
        target: torch.Tensor | None = None,
        region: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """``rgb`` (H, W, 3) times this frame's gains, clipped at 1 as the camera clips. From
        ``start_iter`` on, with ``target`` and ``region`` given, the gains are first re-estimated
        from this draw. A frame never estimated is left as rendered."""
        if not self.enabled or index not in self.slots:
            return rgb
        row = self.slots[index]
        if iteration >= self.start_iter and target is not None and region is not None:
            with torch.no_grad():
                self.estimate(row, rgb.detach(), target, region)
        if int(self.steps[row]) == 0:
            return rgb
        gain = (self.gains[row] - self._mean()).exp()
        return (rgb * gain).clamp(max=1.0)

    def gains_of(self) -> dict[int, np.ndarray]:
        """Frame index -> (3,) gains as applied (linear, not log; 1 for a frame never estimated)."""
        logs = torch.where((self.steps > 0).to(self.device)[:, None], self.gains - self._mean(), 0.0)
        values = logs.exp().cpu().numpy()
        return {frame: values[row] for frame, row in self.slots.items()}

    # --- checkpoints ---------------------------------------------------------------------------
    def state_arrays(self) -> dict[str, np.ndarray]:
        if not self.slots:
            return {}
        frames = sorted(self.slots, key=self.slots.get)
        return {
            "frames": np.asarray(frames, np.float32),  # snapshot arrays are float32: exact below 2^24
            "gains": self.gains.cpu().numpy().astype(np.float32),
            "steps": self.steps.numpy().astype(np.float32),
        }

    def load_state_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        """From :meth:`state_arrays` (a checkpoint of the Adam this replaced: its gains, its moments
        dropped)."""
        if "frames" not in arrays:
            return
        frames = [int(f) for f in np.asarray(arrays["frames"])]
        self.slots = {f: i for i, f in enumerate(frames)}
        gains = np.array(arrays["gains"], np.float32).reshape(-1, 3)
        self.gains = torch.as_tensor(gains, device=self.device)
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


def for_footage(config):
    """``config`` with the colour correction on, as footage from a self-exposing camera needs it;
    a rate the config already sets (a user's ``--set lr_exposure=``, a preset) is kept."""
    if getattr(config, "lr_exposure", None) != 0.0:
        return config
    return config.replace(lr_exposure=FOOTAGE_RATE)
