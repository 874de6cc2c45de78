"""What keeps a fitted pose anatomical: joint-angle limits and a range-of-motion pose prior (torch).

Both reuse the clinical limits of the synthetic benchmark (:mod:`stg_node.data.synth.joint_limits`,
Euler angles ``(x, y, z)`` in each joint's parent frame with ``R = Rz(z) @ Ry(y) @ Rx(x)``):

- :func:`limit_excess`: how far (radians) each joint's Euler angles lie outside its range; the
  fitter penalises it steeply, so the knee does not bend backwards to explain a noisy keypoint.
- :func:`prior_sigma`: a per-joint, per-axis spread for a zero-mean Gaussian prior on the
  axis-angle pose: half the joint's largest excursion (at least :data:`MIN_PRIOR_SIGMA_DEG`).
  Stiff joints (spine, collars, feet) stay near rest unless the image insists; free ones
  (shoulders, hips, knees, elbows) move almost freely. No learned prior (SMPLify's GMM,
  VPoser) ships under a licence we can redistribute, and this one needs no data.

All functions take the 23 non-root joints (SMPL's root rotation stays zero; ``Rh`` carries it).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from stg_node.data.synth.joint_limits import JOINT_LIMITS_DEG

MIN_PRIOR_SIGMA_DEG = 5.0
# Euler y = asin(-R20) loses precision at +-90 degrees; no joint range comes near it.
_ASIN_CLAMP = 1.0 - 1e-7

LIMITS_RAD = np.deg2rad(JOINT_LIMITS_DEG[1:])  # (23, 3, 2) low/high per axis


def euler_zyx_from_matrix(rotations: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotations -> (..., 3) Euler angles (x, y, z), radians, with R = Rz Ry Rx."""
    r20 = rotations[..., 2, 0].clamp(-_ASIN_CLAMP, _ASIN_CLAMP)
    x = torch.atan2(rotations[..., 2, 1], rotations[..., 2, 2])
    y = torch.asin(-r20)
    z = torch.atan2(rotations[..., 1, 0], rotations[..., 0, 0])
    return torch.stack([x, y, z], dim=-1)


def _wrap(angle: torch.Tensor) -> torch.Tensor:
    return torch.remainder(angle + math.pi, 2 * math.pi) - math.pi


def limit_excess(body_rotations: torch.Tensor) -> torch.Tensor:
    """(B, 23, 3, 3) local joint rotations -> (B, 23, 3) radians outside the joint limits (0 inside).

    Every rotation has two Z-Y-X decompositions: ``(x, y, z)`` with ``|y| <= 90`` degrees and
    ``(x + pi, pi - y, z + pi)``. An elbow flexed past 90 degrees (its range reaches 145) is only
    inside its limits in the second, so each joint is judged by the branch that fits it better.
    """
    euler = euler_zyx_from_matrix(body_rotations)
    other = torch.stack(
        [_wrap(euler[..., 0] + math.pi), _wrap(math.pi - euler[..., 1]), _wrap(euler[..., 2] + math.pi)],
        dim=-1,
    )
    limits = torch.as_tensor(LIMITS_RAD, dtype=euler.dtype, device=euler.device)

    def excess(angles):
        return torch.relu(limits[..., 0] - angles) + torch.relu(angles - limits[..., 1])

    first, second = excess(euler), excess(other)
    use_second = second.sum(dim=-1, keepdim=True) < first.sum(dim=-1, keepdim=True)
    return torch.where(use_second, second, first)


def prior_sigma() -> np.ndarray:
    """(23, 3) spread (radians) of the range-of-motion prior per joint and axis."""
    reach = np.maximum(np.abs(LIMITS_RAD[..., 0]), np.abs(LIMITS_RAD[..., 1]))
    return np.maximum(reach / 2.0, np.deg2rad(MIN_PRIOR_SIGMA_DEG))
