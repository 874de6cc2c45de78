"""The non-rigid part: Spacetime Gaussians (polynomial motion and rotation in time, temporal opacity).

For Gaussian i at normalised time u (see :class:`TimeAxis`), with local time
``tau = tanh((u - mu_i^tau) / w_i)``, ``w_i = min(s_i, h)`` (its temporal scale, at most the time
horizon h):

    offset_i(u)  = sum_{k=1..n_p} b_ik tau^k                 (canonical frame, metres)
    q_i(u)       = normalise(q_i + sum_{k=1..n_q} c_ik tau^k)
    sigma_i(u)   = sigma_i exp(-((u - mu_i^tau) / s_i)^2)      (1 for s_i >= PERSISTENT_SCALE)

**Where the offsets act.** The offset is added to the canonical centre *before* skinning, so
the posed centre is ``X_L + R_blend(t) offset_i(u)``: the paper's ``X_L + sum b_ik tau^k`` with
the offset expressed in the Gaussian's own body frame. A swing of the hem learned while the
subject faced the camera stays a swing of the hem, not a fixed direction in the world, when the
subject turns or is re-posed; a world-space offset would be wrong as soon as the body rotates.

**Why time is bounded, and why in units of the window.** Time is counted in fixed units from
the first frame (no sequence length needed, so a stream of unknown length works). Each
polynomial sees its local time in units of its own temporal window, squashed by tanh into
(-1, 1): a Gaussian evaluated far from its temporal centre (frame 10,000 of a stream, or a
static Gaussian whose window spans everything) gets an offset bounded by ``sum_k |b_ik|``, never
a polynomial blow-up, and a coefficient means the same travel (metres at the edge of the
window) whether the window lasts 0.1 s or the whole sequence, so one learning rate fits both.
Near its centre (|u - mu| << w) tanh is the identity to first order, so the polynomial is the
paper's in the rescaled time ``(u - mu) / w``. The window enters tau without gradient: the
temporal scale is learned through the temporal opacity.

**What costs nothing.** A Gaussian whose motion coefficients are all exactly zero (static
regions, driven there by the L1 proximal step in training) is skipped when rendering; with
``skip_inactive`` the polynomial is evaluated only on the active rows.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

# A temporal window this wide (time units) or wider means "present at all times": such Gaussians
# (the body's initial ones, 1000 units) get no temporal opacity at all, so an avatar trained online
# for hours does not fade out of its own stream (docs/STABILITY.md).
PERSISTENT_SCALE = 100.0


@dataclass(frozen=True)
class TimeAxis:
    """Seconds -> normalised time units: ``u = (t - origin_s) / unit_s``."""

    origin_s: float = 0.0
    unit_s: float = 1.0

    def __call__(self, t_seconds: float) -> float:
        return (float(t_seconds) - self.origin_s) / self.unit_s


@dataclass
class SpacetimeState:
    """What the spacetime terms contribute at one instant (None where a term is off)."""

    offsets: torch.Tensor | None  # (N, 3) canonical-frame offset of each centre
    quats: torch.Tensor  # (N, 4) rotation at u, unnormalised
    temporal: torch.Tensor | None  # (N,) temporal opacity factor in (0, 1]


def window(table, horizon: float) -> torch.Tensor:
    """``w_i = min(s_i, h)``, without gradient (see the module docstring)."""
    return table["t_log_scale"].detach().exp().clamp_max(horizon)


def local_time(
    u: float, t_center: torch.Tensor, width: torch.Tensor | float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Raw ``u - mu`` and bounded ``tau = tanh((u - mu) / w)``."""
    dt = u - t_center
    return dt, torch.tanh(dt / width)


def polynomial(coeffs: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
    """``sum_{k=1..K} coeffs[:, k-1] tau^k``: coeffs (N, K, D), tau (N,) -> (N, D)."""
    out = coeffs[:, 0] * tau[:, None]
    power = tau
    for k in range(1, coeffs.shape[1]):
        power = power * tau
        out = out + coeffs[:, k] * power[:, None]
    return out


def evaluate(
    table,
    u: float,
    horizon: float,
    *,
    temporal_opacity: bool,
    skip_inactive: bool = False,
    bases=None,
    rows: torch.Tensor | None = None,
    windowed: torch.Tensor | None = None,
) -> SpacetimeState:
    """The spacetime terms of every Gaussian of ``table`` at normalised time ``u``.

    ``bases``: the model's MotionBases when its offsets are mixtures of shared trajectories.
    ``rows``: evaluate the motion terms of these rows only; every other row keeps a zero offset and
    its base rotation (static Gaussians, whose terms are exact zeros), and only finite temporal
    windows are evaluated (the rest are 1). ``skip_inactive`` takes the rows with a non-zero motion
    term. With no such rows the offsets are None: the rigid part alone, at its cost.
    ``windowed``: the rows whose temporal window is finite, when the caller has them (a renderer
    keeps them between frames); the temporal opacity is then evaluated on those rows only, every
    other row's factor is exactly 1 either way.
    """
    quats = table["quats"]
    motion = table.get("motion")
    coef = table.get("motion_coef") if bases is not None else None
    rot_motion = table.get("rot_motion")
    t_center = table.get("t_center")
    if t_center is None:
        return SpacetimeState(None, quats, None)
    if skip_inactive:
        rows = table.motion_active().nonzero().squeeze(1)
    restricted = rows is not None
    has_offsets = motion is not None or coef is not None
    offsets = None
    if (has_offsets or rot_motion is not None) and (not restricted or rows.numel()):
        width = window(table, horizon)
        if restricted:
            tau = local_time(u, t_center[rows], width[rows])[1]
        else:
            tau = local_time(u, t_center, width)[1]
        if has_offsets:
            if coef is not None:
                means = table["means"]
                offsets = (
                    bases.apply(bases.at(u), coef[rows], means[rows])
                    if restricted
                    else bases.apply(bases.at(u), coef, means)
                )
            else:
                offsets = polynomial(motion[rows] if restricted else motion, tau)
            if restricted:
                offsets = torch.zeros_like(table["means"]).index_put((rows,), offsets)
        if rot_motion is not None:
            if restricted:
                quats = quats.index_put((rows,), quats[rows] + polynomial(rot_motion[rows], tau))
            else:
                quats = quats + polynomial(rot_motion, tau)
    temporal = None
    if temporal_opacity and windowed is not None:
        if windowed.numel():
            log_scale = table["t_log_scale"]
            factor = torch.exp(-(((u - t_center[windowed]) / log_scale[windowed].exp()) ** 2))
            temporal = torch.ones_like(log_scale).index_put((windowed,), factor)
    elif temporal_opacity:
        scale = table["t_log_scale"].exp()
        if restricted:
            finite = (scale.detach() < PERSISTENT_SCALE).nonzero().squeeze(1)
            if finite.numel():
                factor = torch.exp(-(((u - t_center[finite]) / scale[finite]) ** 2))
                temporal = torch.ones_like(scale).index_put((finite,), factor)
        else:
            temporal = torch.exp(-(((u - t_center) / scale) ** 2))
            temporal = torch.where(scale >= PERSISTENT_SCALE, torch.ones_like(temporal), temporal)
    return SpacetimeState(offsets, quats, temporal)


def velocity(table, u: float, horizon: float, bases=None) -> torch.Tensor | None:
    """d offset / du (N, 3) at ``u`` (canonical frame, metres per time unit), or None without motion."""
    if bases is not None and "motion_coef" in table:
        return bases.apply(bases.derivative(u), table["motion_coef"], table["means"])
    motion = table.get("motion")
    if motion is None:
        return None
    w = window(table, horizon)
    dt, tau = local_time(u, table["t_center"], w)
    dtau = (1.0 - tau**2) / w  # d tau / du
    out = motion[:, 0]
    power = torch.ones_like(tau)
    for k in range(1, motion.shape[1]):
        power = power * tau
        out = out + (k + 1) * motion[:, k] * power[:, None]
    return out * dtau[:, None]
