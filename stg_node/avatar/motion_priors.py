"""Priors that make a monocular capture's non-rigid motion generalise to views it never saw.

From one camera, image evidence constrains a Gaussian's motion across the image plane only: a
displacement along the camera's line of sight changes nothing the training view sees (to first
order), so free non-rigid offsets spend that freedom on placements every other view disagrees
with. Shape of Motion (Wang et al. 2024) and MoSca penalise motion along the ray; we do the
same for the spacetime offsets:

    L_los = sum_i w_i |<R_i offset_i(t), r_i>| / sum_i w_i         (cm)

with ``R_i offset_i(t)`` the world displacement the offset causes under skinning (the blended
bone transform's linear part applied to the canonical offset), ``r_i`` the unit ray from the
training camera's centre to the Gaussian's posed centre, and ``w_i`` its temporal opacity at
``t`` (without gradient): a copy absent at this instant is not held to this view.
"""

from __future__ import annotations

import torch

from stg_node.avatar.rigid import PosedBones, blend


def world_offsets(offsets: torch.Tensor, weights: torch.Tensor, bones: PosedBones) -> torch.Tensor:
    """(M, 3) world displacement of canonical ``offsets`` (M, 3) under skinning ``weights`` (M, 24)."""
    linear = blend(weights, bones)[:, :3, :3]
    return (linear @ offsets[..., None]).squeeze(-1)


def line_of_sight(
    displacement: torch.Tensor,
    posed_means: torch.Tensor,
    camera_center: torch.Tensor,
    presence: torch.Tensor | None = None,
) -> torch.Tensor:
    """Mean |component of ``displacement`` (M, 3, metres) along the ray camera -> ``posed_means``| in cm,
    weighted by ``presence`` (M,) when given; 0 for no rows."""
    if displacement.shape[0] == 0:
        return displacement.new_zeros(())
    ray = posed_means.detach() - camera_center.to(posed_means)
    ray = ray / ray.norm(dim=1, keepdim=True).clamp_min(1e-9)
    along = 100.0 * (displacement * ray).sum(dim=1).abs()
    if presence is None:
        return along.mean()
    w = presence.detach()
    return (w * along).sum() / w.sum().clamp_min(1e-6)
