"""Garment-like non-rigid deformation that skinning cannot explain: a loose hem and two sleeves.

The benchmark's subject wears, in effect, a loose shirt: the band of the body surface from
the chest down to a hem line at the waist, and the upper arms from the shoulder to a sleeve
end short of the elbow, are cloth (matching the shirt painted on the open body's texture).
Each cloth vertex is a damped mass on a spring attached to where skinning puts it, in the
world frame and moving through still air::

    d'' + (2 zeta w + c) d' + w^2 d = -(x'' + c x')

where ``x(t)`` is the skinned (LBS) position, ``d`` the cloth's offset from it, ``w`` the
natural frequency, ``zeta`` the damping ratio and ``c`` an air-drag rate. The inertial term
``-x''`` makes the hem lag and overshoot when the body accelerates (turning, stopping,
dancing); the drag term ``-c x'`` makes it trail steadily behind a moving limb
(about ``c |x'| / w^2``), so the deformation grows with limb velocity and vanishes for a
body at rest. The natural frequency varies a little around the hem and each sleeve (a
``ripple`` in azimuth), so the cloth ripples instead of moving as one block.

The offset is weighted by how loose the cloth is at each vertex (0 where it is attached at
the chest and shoulders, 1 at the hem line and sleeve ends, fading back to 0 on the skin
just below), and its length is soft-clamped to ``max_offset_m`` with tanh. Integration is
trapezoidal (Crank-Nicolson: second order, unconditionally stable) with ``substeps`` steps
per frame; the skinned velocity and acceleration (central and compact second differences of
the per-frame positions) are interpolated linearly between frames. It is deterministic and
starts at the quasi-static equilibrium (zero for a body at rest). The written SMPL
parameters never include these offsets; the ground-truth vertices do.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from stg_node.data.synth.joint_limits import JOINT_INDEX


@dataclass(frozen=True)
class GarmentParams:
    """Physical parameters of the cloth response (SI units)."""

    natural_freq_hz: float = 1.5
    damping_ratio: float = 0.3
    drag_per_s: float = 4.0
    max_offset_m: float = 0.08
    ripple: float = 0.2  # relative spread of the natural frequency around hem and sleeves
    substeps: int = 4
    # Where the cloth is, in the rest pose. The defaults match the shirt painted on the open
    # body's texture: it hangs from the chest (spine3), ends just below the spine1 joint, and
    # its sleeves cover 45 % of the upper arm.
    hem_attach_joint: str = "spine3"
    hem_joint: str = "spine1"
    hem_below_joint_m: float = 0.015  # the hem line, this far below hem_joint
    sleeve_fraction: float = 0.45  # sleeve end as a fraction of the shoulder-to-elbow length
    fade_m: float = 0.05  # cloth-to-skin fade below the hem / beyond the sleeve end

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class GarmentRegions:
    """Per-vertex looseness of the cloth and the ripple of its natural frequency."""

    weight: np.ndarray  # (V,) in [0, 1]; 0 = skin or attached cloth, 1 = free hem / sleeve end
    freq_scale: np.ndarray  # (V,) multiplies GarmentParams.natural_freq_hz
    hem: np.ndarray  # (V,) bool: vertex belongs to the hem region
    sleeves: np.ndarray  # (V,) bool: vertex belongs to a sleeve

    @property
    def indices(self) -> np.ndarray:
        """Indices of the vertices that move (weight > 0)."""
        return np.flatnonzero(self.weight > 0)


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _loose_profile(s: np.ndarray, fade: float) -> np.ndarray:
    """Looseness along a garment coordinate ``s`` (0 = attachment, 1 = free edge, >1 = skin beyond).

    ``fade`` is the length of the fade back to skin, in units of ``s``.
    """
    rise = _smoothstep(s)
    fall = 1.0 - _smoothstep((s - 1.0) / max(fade, 1e-9))
    return np.where(s <= 1.0, rise, fall) * (s > 0)


def garment_regions(
    rest_vertices: np.ndarray, rest_joints: np.ndarray, params: GarmentParams | None = None
) -> GarmentRegions:
    """Hem and sleeve regions from the body in its rest (T-) pose, in SMPL coordinates (y up, x left).

    ``rest_vertices`` (V, 3) and ``rest_joints`` (24, 3) must be the body at zero pose with
    no global rotation or translation.
    """
    params = params or GarmentParams()
    v = np.asarray(rest_vertices, dtype=np.float64)
    j = np.asarray(rest_joints, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"rest_vertices must be (V, 3), got {v.shape}")
    if j.shape != (24, 3):
        raise ValueError(f"rest_joints must be (24, 3) in SMPL order, got {j.shape}")

    # Hem: loose from the attachment height (chest) down to the hem line.
    for name in (params.hem_attach_joint, params.hem_joint):
        if name not in JOINT_INDEX:
            raise ValueError(f"unknown SMPL joint {name!r} in GarmentParams")
    attach_y = j[JOINT_INDEX[params.hem_attach_joint], 1]
    hem_y = j[JOINT_INDEX[params.hem_joint], 1] - params.hem_below_joint_m
    length = attach_y - hem_y
    if length <= 0:
        raise ValueError(f"the hem line ({hem_y:.3f} m) must lie below its attachment ({attach_y:.3f} m)")
    s_hem = (attach_y - v[:, 1]) / length
    hem_weight = _loose_profile(s_hem, params.fade_m / length)
    # Only the torso and thighs: exclude anything beyond the shoulders sideways (hands, arms).
    shoulder_x = 0.5 * (j[JOINT_INDEX["left_shoulder"], 0] - j[JOINT_INDEX["right_shoulder"], 0])
    centre = j[JOINT_INDEX["pelvis"]]
    hem_weight = np.where(np.abs(v[:, 0] - centre[0]) < shoulder_x, hem_weight, 0.0)
    hem_azimuth = np.arctan2(v[:, 0] - centre[0], v[:, 2] - centre[2])
    hem_scale = 1.0 + params.ripple * np.sin(3.0 * hem_azimuth)

    sleeve_weight = np.zeros(len(v))
    sleeve_scale = np.ones(len(v))
    for side, sign in (("left", 1.0), ("right", -1.0)):
        shoulder = j[JOINT_INDEX[f"{side}_shoulder"]]
        elbow = j[JOINT_INDEX[f"{side}_elbow"]]
        axis = elbow - shoulder
        bone = np.linalg.norm(axis)
        axis = axis / bone
        sleeve_len = params.sleeve_fraction * bone
        along = (v - shoulder) @ axis
        radial = np.linalg.norm((v - shoulder) - along[:, None] * axis, axis=1)
        s = along / sleeve_len
        # Arms only: far enough out sideways and close to the upper-arm bone.
        on_arm = (sign * (v[:, 0] - shoulder[0]) > 0) & (radial < 0.5 * bone)
        w = np.where(on_arm, _loose_profile(s, params.fade_m / sleeve_len), 0.0)
        azimuth = np.arctan2(v[:, 1] - shoulder[1], v[:, 2] - shoulder[2])
        sleeve_scale = np.where(w > 0, 1.0 + params.ripple * np.sin(2.0 * azimuth), sleeve_scale)
        sleeve_weight = np.maximum(sleeve_weight, w)

    weight = np.maximum(hem_weight, sleeve_weight)
    freq_scale = np.where(hem_weight >= sleeve_weight, hem_scale, sleeve_scale)
    return GarmentRegions(weight=weight, freq_scale=freq_scale, hem=hem_weight > 0, sleeves=sleeve_weight > 0)


def simulate_garment(
    trajectory: np.ndarray,
    weight: np.ndarray,
    fps: float,
    params: GarmentParams | None = None,
    freq_scale: np.ndarray | None = None,
) -> np.ndarray:
    """Cloth offsets (T, V, 3) for skinned world positions ``trajectory`` (T, V, 3) sampled at ``fps``.

    Only vertices with ``weight > 0`` are simulated; the others get exactly zero.
    """
    params = params or GarmentParams()
    x = np.asarray(trajectory, dtype=np.float64)
    if x.ndim != 3 or x.shape[2] != 3:
        raise ValueError(f"trajectory must be (T, V, 3), got {x.shape}")
    weight = np.asarray(weight, dtype=np.float64)
    if weight.shape != (x.shape[1],):
        raise ValueError(f"weight must be (V,) = ({x.shape[1]},), got {weight.shape}")
    if not np.isfinite(x).all():
        raise ValueError("trajectory contains NaN or inf")
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    scale = np.ones(x.shape[1]) if freq_scale is None else np.asarray(freq_scale, dtype=np.float64)

    offsets = np.zeros_like(x)
    active = np.flatnonzero(weight > 0)
    num_frames = x.shape[0]
    if active.size == 0 or num_frames < 2:
        return offsets.astype(np.float32)

    dt = 1.0 / fps
    xa = x[:, active]
    velocity = np.gradient(xa, dt, axis=0)
    # Compact second difference (error ~(w dt)^2 / 12, four times smaller than differencing twice).
    acceleration = np.zeros_like(xa)
    if num_frames >= 3:
        acceleration[1:-1] = (xa[2:] - 2.0 * xa[1:-1] + xa[:-2]) / (dt * dt)
        acceleration[0], acceleration[-1] = acceleration[1], acceleration[-2]
    drive = -(acceleration + params.drag_per_s * velocity)  # (T, A, 3)

    omega = (2 * np.pi * params.natural_freq_hz * scale[active])[:, None]  # (A, 1)
    omega2 = omega * omega
    friction = 2 * params.damping_ratio * omega + params.drag_per_s
    substeps = max(int(params.substeps), 1)
    h = dt / substeps
    # Trapezoidal (Crank-Nicolson) steps of s' = A s + (0, u), A = [[0, 1], [-w^2, -friction]]:
    # (I - hA/2) s+ = (I + hA/2) s + h/2 (0, u + u+), solved in closed form per vertex.
    det = 1.0 + 0.5 * h * friction + 0.25 * h * h * omega2  # det(I - hA/2)
    m00 = (1.0 + 0.5 * h * friction - 0.25 * h * h * omega2) / det
    m01 = h / det
    m10 = -h * omega2 / det
    m11 = (1.0 - 0.5 * h * friction - 0.25 * h * h * omega2) / det
    n0 = 0.25 * h * h / det  # effect of h/2 (u + u+) on d+
    n1 = 0.5 * h / det  # ... and on d'+

    d = drive[0] / omega2  # quasi-static start
    d_dot = np.zeros_like(d)
    out = np.empty_like(xa)
    out[0] = d
    for n in range(num_frames - 1):
        u0, du = drive[n], (drive[n + 1] - drive[n]) / substeps
        for k in range(substeps):
            u_sum = 2.0 * u0 + (2 * k + 1) * du  # u(k) + u(k + 1), linear in between frames
            d, d_dot = m00 * d + m01 * d_dot + n0 * u_sum, m10 * d + m11 * d_dot + n1 * u_sum
        out[n + 1] = d

    # Soft clamp of the offset length, then the looseness weight.
    length = np.linalg.norm(out, axis=-1, keepdims=True)
    limit = params.max_offset_m
    factor = np.where(length > 1e-12, limit * np.tanh(length / limit) / np.maximum(length, 1e-12), 1.0)
    offsets[:, active] = out * factor * weight[active][None, :, None]
    return offsets.astype(np.float32)
