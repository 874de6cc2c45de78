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

Windowed knots: the bases hold the knots whose grid indices are ``knot_ids`` (ascending; knot
``knot_ids[k]`` at time ``knot_ids[k] * knot_units``), by default ``0..K-1``. A bounded trainer
(its frame store evicts) keeps only the knots around the frames it still holds
(:meth:`MotionBases.kept`): knots no held frame reaches carry no data term any more, and
without the cut an online stream would grow them without limit. Between two held knots the
motion is linear (in the contiguous case exactly the knots' own segments); before the first
held knot it holds the first one's value, after the last the last one's.

Basis ``b`` belongs to the body's bones ``j`` with ``floor(j B / 24) = b`` (24 bases: one per
bone, GART's latent bones); a Gaussian that starts to move starts with its skinning weights
summed that way as coefficients (:func:`initial_coefficients`), and learns them from there.
The offset acts where the polynomial's does (before skinning, see spacetime.py), so everything
downstream (rigidity, line of sight, the flow loss, the motion gate) is unchanged.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

NUM_BONES = 24
#: Knots kept either side of a held frame's reach when a bounded trainer drops the others.
KNOT_MARGIN = 2


def initial_coefficients(skin_weights: torch.Tensor, count: int) -> torch.Tensor:
    """(M, count) coefficients of Gaussians that start to move: their skinning weights (M, 24)
    summed over the bones of each basis. The motions start at zero, so the offsets start at zero,
    yet both factors get a gradient from the first step."""
    if count == NUM_BONES:  # one bone per basis: the weights themselves (no scatter over 24 columns)
        return skin_weights.clone()
    group = torch.arange(NUM_BONES, device=skin_weights.device) * count // NUM_BONES
    out = skin_weights.new_zeros(skin_weights.shape[0], count)
    return out.index_add_(1, group, skin_weights)


class MotionBases(nn.Module):
    """``count`` affine motions ``(count, knots, 3, 4)``; stored knot k at time ``knot_ids[k] *
    knot_units`` (time units), ``knot_ids`` ``0..knots-1`` unless windowed (module docstring)."""

    def __init__(
        self,
        count: int,
        knot_units: float,
        knots: int = 2,
        values: torch.Tensor | None = None,
        knot_ids=None,
    ):
        super().__init__()
        if count < 1 or not knot_units > 0:
            raise ValueError(f"MotionBases needs count >= 1 and knot_units > 0, got {count}, {knot_units}")
        self.knot_units = float(knot_units)
        if values is None:
            values = torch.zeros(count, max(int(knots), 2), 3, 4)
        if values.dim() != 4 or values.shape[0] != count or values.shape[2:] != (3, 4) or values.shape[1] < 2:
            raise ValueError(f"motion bases must be ({count}, K >= 2, 3, 4), got {tuple(values.shape)}")
        self.values = nn.Parameter(values.detach().clone().float())
        self.knot_ids = self._checked_ids(knot_ids, self.knots)

    @staticmethod
    def _checked_ids(knot_ids, knots: int) -> np.ndarray:
        if knot_ids is None:
            return np.arange(knots, dtype=np.int64)
        ids = np.asarray(knot_ids).reshape(-1)
        if ids.shape[0] != knots or (ids.size and (ids[0] < 0 or np.any(np.diff(ids) <= 0))):
            raise ValueError(f"knot ids must be {knots} ascending indices >= 0, got {ids.tolist()[:8]}...")
        if not np.array_equal(ids, np.round(ids)):
            raise ValueError("knot ids must be whole numbers")
        return ids.astype(np.int64)

    @property
    def count(self) -> int:
        return int(self.values.shape[0])

    @property
    def knots(self) -> int:
        return int(self.values.shape[1])

    @property
    def first_knot(self) -> int:
        """Grid index of the first knot held (0 unless a bounded trainer dropped older ones)."""
        return int(self.knot_ids[0])

    @property
    def contiguous(self) -> bool:
        return int(self.knot_ids[-1] - self.knot_ids[0]) == self.knots - 1

    def _place(self, u: float) -> tuple[int, float]:
        """Stored knot index k and fraction f of ``u`` between stored knots k and k+1, clamped to the
        knots held."""
        ids = self.knot_ids
        x = min(max(float(u) / self.knot_units, float(ids[0])), float(ids[-1]))
        if self.contiguous:
            y = x - int(ids[0])
            k = min(int(math.floor(y)), self.knots - 2)
            return k, y - k
        k = min(max(int(np.searchsorted(ids, x, side="right")) - 1, 0), self.knots - 2)
        return k, (x - int(ids[k])) / int(ids[k + 1] - ids[k])

    def at(self, u: float) -> torch.Tensor:
        """(count, 3, 4) every affine motion at time ``u``."""
        k, f = self._place(u)
        return (1.0 - f) * self.values[:, k] + f * self.values[:, k + 1]

    def derivative(self, u: float) -> torch.Tensor:
        """(count, 3, 4) d A / du (per time unit); 0 outside the knots' span."""
        x = float(u) / self.knot_units
        if x < self.knot_ids[0] or x > self.knot_ids[-1]:
            return torch.zeros_like(self.values[:, 0])
        k, _ = self._place(u)
        gap = int(self.knot_ids[k + 1] - self.knot_ids[k])
        return (self.values[:, k + 1] - self.values[:, k]) / (self.knot_units * gap)

    @staticmethod
    def apply(motions: torch.Tensor, coef: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """``sum_b coef[:, b] motions[b] [points; 1]``: (M, 3) from motions (B, 3, 4), coef (M, B),
        points (M, 3) canonical centres (taken without gradient: the motion moves them, not the
        other way round)."""
        p = points.detach()
        mixed = torch.einsum("mb,bij->mij", coef, motions)  # (M, 3, 4)
        return (mixed[:, :, :3] @ p[..., None]).squeeze(-1) + mixed[:, :, 3]

    @torch.no_grad()
    def grown(self, u: float) -> torch.Tensor | None:
        """The values extended (last knot repeated) so that ``u`` lies within the knots, or None;
        the new knots follow the last one (:meth:`install` them at :meth:`grown_ids`)."""
        extra = max(int(math.ceil(float(u) / self.knot_units)), 1) - int(self.knot_ids[-1])
        if extra <= 0:
            return None
        tail = self.values[:, -1:].expand(-1, extra, -1, -1)
        return torch.cat([self.values.detach(), tail], dim=1)

    def grown_ids(self, knots: int) -> np.ndarray:
        """The knot ids after growing to ``knots`` knots (the new ones follow the last held one)."""
        last = int(self.knot_ids[-1])
        return np.concatenate([self.knot_ids, np.arange(last + 1, last + 1 + knots - self.knots)])

    def kept(self, spans) -> np.ndarray:
        """(K,) bool: the stored knots to keep for frames at the time ``spans`` ((F, 2) time units,
        each ``[start, end]`` a held frame's reach), ``KNOT_MARGIN`` knots either side, and always
        the last knot (the stream's newest end, where growth continues)."""
        keep = np.zeros(self.knots, bool)
        keep[-1] = True
        ids = self.knot_ids
        for start, end in np.asarray(spans, np.float64).reshape(-1, 2):
            lo = math.floor(start / self.knot_units) - KNOT_MARGIN
            hi = math.ceil(end / self.knot_units) + KNOT_MARGIN
            keep[int(np.searchsorted(ids, lo, "left")) : int(np.searchsorted(ids, hi, "right"))] = True
        if keep.sum() < 2:  # at least one segment
            keep[-2] = True
        return keep

    def install(self, values: torch.Tensor, knot_ids) -> nn.Parameter:
        """Hold ``values`` at ``knot_ids`` (a new Parameter); returns the old one (for the optimiser)."""
        ids = self._checked_ids(knot_ids, int(values.shape[1]))
        old = self.values
        self.values = nn.Parameter(values.detach().to(old.device))
        self.knot_ids = ids
        return old

    def roughness(self, reach_m: float = 1.0) -> torch.Tensor:
        """Mean |second difference| of the knots (cm at ``reach_m`` from the origin): the motions
        stay smooth between frames."""
        v = self.values
        if v.shape[1] < 3:
            return v.new_zeros(())
        second = v[:, 2:] - 2 * v[:, 1:-1] + v[:, :-2]  # (B, K-2, 3, 4)
        per = reach_m * second[..., :3].abs().sum((-1, -2)) + second[..., 3].abs().sum(-1)  # (B, K-2)
        if self.contiguous:
            return 100.0 * per.mean()
        # windowed: only triples of consecutive grid knots (no second difference across a gap)
        ids = self.knot_ids
        run = torch.as_tensor((ids[2:] - ids[:-2]) == 2, device=v.device)
        if not bool(run.any()):
            return v.new_zeros(())
        return 100.0 * per[:, run].mean()

    @torch.no_grad()
    def variation(self, coef: torch.Tensor, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(M,) how far each row's offset strays over the knots from its mean over them (metres), and
        (M, 3) that mean: a constant offset is a displaced centre, not motion. Two passes over the
        knots, so memory stays (M, 3) however many knots a long stream has."""
        if coef.shape[0] == 0:
            return coef.new_zeros(0), coef.new_zeros(0, 3)
        p = torch.cat([points, torch.ones_like(points[:, :1])], dim=1)[..., None]  # (M, 4, 1)

        def offset(k: int) -> torch.Tensor:
            return (torch.einsum("mb,bij->mij", coef, self.values[:, k]) @ p).squeeze(-1)

        mean = sum(offset(k) for k in range(self.knots)) / self.knots
        swing = coef.new_zeros(coef.shape[0])
        for k in range(self.knots):
            swing = torch.maximum(swing, (offset(k) - mean).norm(dim=1))
        return swing, mean
