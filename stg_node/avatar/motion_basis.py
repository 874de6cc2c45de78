"""Shared motion bases: non-rigid offsets as per-Gaussian mixtures of a few shared affine motions.

Spacetime Gaussians give every Gaussian its own polynomial in time. From one camera that is
more freedom than the images constrain: a Gaussian learns its offset only at the instants it is
seen, and the side of the garment facing away at time t has nothing to go on. Shape of Motion
(Wang et al. 2024: SE(3) motion bases) and GART (Lei et al. 2024: latent bones for loose
clothing) share motion instead. Here

    offset_i(u) = sum_b c_ib A_b(u) [x_i; 1]                       (canonical frame, metres)

with ``B`` shared *affine* motions ``A_b(u)`` (3 x 4: a linear part and a translation, acting on
the Gaussian's canonical centre ``x_i``), piecewise linear in time over knots every
``basis_knot_s`` seconds from the time axis' origin (held beyond the last knot), and
per-Gaussian coefficients ``c_i`` (table column ``motion_coef``). Why affine: over a body part,
inertia and drag move cloth by the part's acceleration field, which for a rigid part is affine
in position (``a + alpha x r + omega x (omega x r)``); one affine motion per part at each instant
explains the hem's front and back together, so the side unseen at time t moves with the side
that was seen. Why mixtures: looseness varies over the garment (nothing at the seam, most at
the hem), and parts meet. The knots make the motions as flexible in time as the frame rate (no
temporal copies needed) and grow with the time the trainer has seen (a stream of unknown
length works).

Basis ``b`` belongs to the body's bones ``j`` with ``floor(j B / 24) = b`` (24 bases: one per
bone, GART's latent bones); a Gaussian that starts to move starts with its skinning weights
summed that way as coefficients (:func:`initial_coefficients`), and learns them from there.
The offset acts where the polynomial's does (before skinning, see spacetime.py), so everything
downstream (rigidity, line of sight, the flow loss, the motion gate) is unchanged.
"""

from __future__ import annotations

import math

import torch
from torch import nn

NUM_BONES = 24


def initial_coefficients(skin_weights: torch.Tensor, count: int) -> torch.Tensor:
    """(M, count) coefficients of Gaussians that start to move: their skinning weights (M, 24)
    summed over the bones of each basis. The motions start at zero, so the offsets start at zero,
    yet both factors get a gradient from the first step."""
    group = torch.arange(NUM_BONES, device=skin_weights.device) * count // NUM_BONES
    out = skin_weights.new_zeros(skin_weights.shape[0], count)
    return out.index_add_(1, group, skin_weights)


class MotionBases(nn.Module):
    """``count`` affine motions ``(count, knots, 3, 4)``, knot k at time ``k * knot_units`` (time units)."""

    def __init__(self, count: int, knot_units: float, knots: int = 2, values: torch.Tensor | None = None):
        super().__init__()
        if count < 1 or not knot_units > 0:
            raise ValueError(f"MotionBases needs count >= 1 and knot_units > 0, got {count}, {knot_units}")
        self.knot_units = float(knot_units)
        if values is None:
            values = torch.zeros(count, max(int(knots), 2), 3, 4)
        if values.dim() != 4 or values.shape[0] != count or values.shape[2:] != (3, 4) or values.shape[1] < 2:
            raise ValueError(f"motion bases must be ({count}, K >= 2, 3, 4), got {tuple(values.shape)}")
        self.values = nn.Parameter(values.detach().clone().float())

    @property
    def count(self) -> int:
        return int(self.values.shape[0])

    @property
    def knots(self) -> int:
        return int(self.values.shape[1])

    def _place(self, u: float) -> tuple[int, float]:
        """Knot index k and fraction f with ``u = (k + f) * knot_units``, clamped to the knots."""
        x = min(max(float(u) / self.knot_units, 0.0), self.knots - 1.0)
        k = min(int(math.floor(x)), self.knots - 2)
        return k, x - k

    def at(self, u: float) -> torch.Tensor:
        """(count, 3, 4) every affine motion at time ``u``."""
        k, f = self._place(u)
        return (1.0 - f) * self.values[:, k] + f * self.values[:, k + 1]

    def derivative(self, u: float) -> torch.Tensor:
        """(count, 3, 4) d A / du (per time unit); 0 outside the knots' span."""
        x = float(u) / self.knot_units
        if x < 0 or x > self.knots - 1:
            return torch.zeros_like(self.values[:, 0])
        k, _ = self._place(u)
        return (self.values[:, k + 1] - self.values[:, k]) / self.knot_units

    @staticmethod
    def apply(motions: torch.Tensor, coef: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """``sum_b coef[:, b] motions[b] [points; 1]``: (M, 3) from motions (B, 3, 4), coef (M, B),
        points (M, 3) canonical centres (taken without gradient: the motion moves them, not the
        other way round)."""
        p = points.detach()
        mixed = torch.einsum("mb,bij->mij", coef, motions)  # (M, 3, 4)
        return (mixed[:, :, :3] @ p[..., None]).squeeze(-1) + mixed[:, :, 3]

    def knots_to_cover(self, u: float) -> int:
        return max(int(math.ceil(float(u) / self.knot_units)) + 1, 2)

    @torch.no_grad()
    def grown(self, u: float) -> torch.Tensor | None:
        """The values extended (last knot repeated) so that ``u`` lies within the knots, or None."""
        need = self.knots_to_cover(u)
        if need <= self.knots:
            return None
        extra = self.values[:, -1:].expand(-1, need - self.knots, -1, -1)
        return torch.cat([self.values.detach(), extra], dim=1)

    def roughness(self, reach_m: float = 1.0) -> torch.Tensor:
        """Mean |second difference| of the knots (cm at ``reach_m`` from the origin): the motions
        stay smooth between frames."""
        v = self.values
        if v.shape[1] < 3:
            return v.new_zeros(())
        second = v[:, 2:] - 2 * v[:, 1:-1] + v[:, :-2]  # (B, K-2, 3, 4)
        return 100.0 * (reach_m * second[..., :3].abs().sum((-1, -2)) + second[..., 3].abs().sum(-1)).mean()

    @torch.no_grad()
    def amplitude(self, coef: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """(M,) the largest offset each row's mixture reaches over the knots (metres)."""
        if coef.shape[0] == 0:
            return coef.new_zeros(0)
        p = torch.cat([points, torch.ones_like(points[:, :1])], dim=1)  # (M, 4)
        best = coef.new_zeros(coef.shape[0])
        for k in range(self.knots):
            mixed = torch.einsum("mb,bij->mij", coef, self.values[:, k])
            best = torch.maximum(best, (mixed @ p[..., None]).squeeze(-1).norm(dim=1))
        return best
