"""How well shaped a trained avatar's Gaussians are for poses it never saw: needles and torn skinning.

Two things make streaks under extrapolated poses, and both are visible in the model itself,
before any render:

- **anisotropy**: a Gaussian much longer in one axis than in the other two (a needle: largest /
  middle axis) is harmless while it lies inside a limb in the training poses and sticks out of
  it as soon as a joint bends further than training did. A disc (largest / smallest large,
  largest / middle near 1) is a surface element and harmless. Skinning turns a Gaussian without
  stretching it (rigid.py), so the rendered scales are the canonical ones in every pose.
- **skinning disagreement**: neighbours in canonical space whose effective skinning weights
  differ follow different bones; under a pose far from training they tear apart, and a splat
  between them is dragged across the gap. Measured per Gaussian as the mean over its ``k``
  canonical neighbours of the total-variation distance between the two weight vectors
  (``0.5 * sum_b |w_ib - w_jb|``: 0 the same blend, 1 disjoint bones), for the effective weights
  and, for comparison, the body's own weights the model started from (smooth by construction:
  what exceeds them is learned).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch

from stg_node.avatar.isometry import K_NEIGHBOURS, approximate_knn

PERCENTILES = (50.0, 90.0, 99.0)


def _percentiles(values: torch.Tensor) -> dict[str, float]:
    if values.numel() == 0:
        return {f"p{q:g}": float("nan") for q in PERCENTILES}
    v = values.detach().double().cpu()
    return {f"p{q:g}": float(torch.quantile(v, q / 100.0)) for q in PERCENTILES}


def axis_ratios(scales: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(largest / smallest, largest / middle) axis of each of ``scales`` (N, 3)."""
    s = scales.detach().sort(dim=1).values.clamp_min(1e-12)
    return s[:, 2] / s[:, 0], s[:, 2] / s[:, 1]


def neighbour_disagreement(weights: torch.Tensor, neighbours: torch.Tensor) -> torch.Tensor:
    """(N,) mean total-variation distance between each row of ``weights`` (N, B) and its
    ``neighbours`` (N, k) rows."""
    if neighbours.shape[1] == 0:
        return weights.new_zeros(weights.shape[0])
    diff = (weights[:, None, :] - weights[neighbours]).abs().sum(dim=2) * 0.5
    return diff.mean(dim=1)


@dataclass(frozen=True)
class ShapeStats:
    """Percentiles over a model's Gaussians (keys ``p50``, ``p90``, ``p99``)."""

    gaussians: int
    scale_ratio: dict  # largest / smallest axis
    needle_ratio: dict  # largest / middle axis: a needle is long in one axis only
    skin_disagreement: dict  # effective weights against the k canonical neighbours (0..1)
    body_skin_disagreement: dict  # the body's weights the model started from, the same way

    def to_dict(self) -> dict:
        return asdict(self)


@torch.no_grad()
def shape_stats(model, k: int = K_NEIGHBOURS) -> ShapeStats:
    """The anisotropy and skinning-disagreement distributions of ``model`` (an AvatarModel)."""
    table = model.table
    scale_ratio, needle_ratio = axis_ratios(model.scales())
    neighbours = approximate_knn(table["means"].detach(), k)
    effective = neighbour_disagreement(model.skin_weights().detach(), neighbours)
    body = neighbour_disagreement(table["skin_weights"].detach(), neighbours)
    return ShapeStats(
        gaussians=table.num,
        scale_ratio=_percentiles(scale_ratio),
        needle_ratio=_percentiles(needle_ratio),
        skin_disagreement=_percentiles(effective),
        body_skin_disagreement=_percentiles(body),
    )
