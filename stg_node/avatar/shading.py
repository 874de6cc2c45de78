"""Colour that knows where the light is: albedo times the light a Gaussian's surface receives.

The colour model (the light MLP or per-Gaussian SH, :mod:`color`) gives each Gaussian a colour
that turns with the body: it cannot know where the room's light is. A subject that turns
relative to a fixed light shows every surface under a light that changed, and a colour baked
under the training clip's light is wrong for every orientation the clip did not show. This stage
separates the two: the colour model's output is the surface's **albedo**, and the rendered colour
is

    c_i = albedo_i * E(n_i)

where ``n_i`` is the Gaussian's normal in the world and ``E`` the irradiance of a low-order light
fixed in the world (the dataset's frame, the room), learned from the training clip with
everything else:

- **Normal**: the Gaussian's shortest axis, turned by its posed rotation (skinning, then its own
  rotation), flipped to face the camera: for a surface seen from outside the visible side faces
  the viewer, and a splat's axis has no sign of its own. Gaussians start as flat discs along the
  body surface (``model.init_flatness``) so the shortest axis is the surface normal from the start.
- **Light**: second-order spherical-harmonic irradiance (Ramamoorthi and Hanrahan 2001),
  ``E(n) = max(0, sum_k e_k Y_k(n))`` over the 9 real SH functions of :func:`color.sh_basis`,
  per colour channel: 27 numbers. It represents the irradiance of any distant light to within a
  few percent (the clamped-cosine kernel has almost no energy above band 2). The constant term
  is held at ``E = 1`` (mean irradiance over the sphere): brightness and colour of the surface
  stay in the albedo, so albedo and light cannot trade a common scale; the 24 other numbers are
  learned, with a small penalty (``loss.light``) that keeps them at zero (uniform light) unless
  the images ask otherwise. A clip that never turns constrains the light only through the normals
  it shows, and then the penalty leaves it near uniform: the avatar degrades to the baked colour.

Render modes (:class:`LightSpec`): ``learned`` (the default: the learned light, fixed in the
world, so a turning avatar is lit by the room as it turns), ``given`` (a caller's light: SH
coefficients, or directional lights and an ambient term converted exactly to them by
:func:`directional_irradiance`), ``baked`` (the learned light carried along with the body, as if
it never turned from its mean training orientation: what a colour without shading gives, for
comparison) and ``albedo`` (no shading: E = 1).

SH convention: :func:`color.sh_basis` (3DGS's real SH with its signs), world frame of the
dataset. Irradiance coefficients are stored, i.e. ``e_lm = A_l L_lm`` with the radiance's SH
coefficients ``L_lm`` and the clamped-cosine kernel ``A = (pi, 2 pi / 3, pi / 4)``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from stg_node.avatar.color import SH_C0, sh_basis

SH_BANDS = 9  # second order: l = 0, 1, 2
KERNEL = (math.pi,) + (2.0 * math.pi / 3.0,) * 3 + (math.pi / 4.0,) * 5  # clamped cosine, per coefficient
UNIFORM_DC = 1.0 / SH_C0  # e_00 of E(n) = 1 everywhere
LIGHT_MODES = ("learned", "baked", "albedo", "given")


def irradiance(normals: torch.Tensor, coefficients: torch.Tensor) -> torch.Tensor:
    """(N, 3) irradiance at unit ``normals`` (N, 3) of SH irradiance ``coefficients`` (9, 3), >= 0."""
    return (sh_basis(2, normals) @ coefficients).clamp_min(0.0)


def directional_irradiance(directions, colors, ambient=(0.0, 0.0, 0.0), dtype=torch.float32) -> torch.Tensor:
    """(9, 3) SH irradiance of distant lights: ``ambient + sum_k colour_k max(0, n . d_k)``.

    ``directions`` (K, 3): towards each light (normalised here); ``colors`` (K, 3) RGB. A
    directional light's radiance is ``colour delta(w - d)``, whose SH coefficients are
    ``colour Y_lm(d)``; irradiance multiplies band l by the clamped-cosine kernel ``A_l``. The
    result is exact for the ambient term and the best second-order approximation of each clamped
    cosine lobe (within 10 % of the lobe's peak at worst, mostly on the far side; 3 % on average).
    """
    d = torch.as_tensor(np.asarray(directions, np.float64)).reshape(-1, 3)
    c = torch.as_tensor(np.asarray(colors, np.float64)).reshape(-1, 3)
    if d.shape[0] != c.shape[0]:
        raise ValueError(f"{d.shape[0]} light directions but {c.shape[0]} colours")
    norms = d.norm(dim=1, keepdim=True)
    if bool((norms < 1e-9).any()):
        raise ValueError("a light direction is zero")
    basis = sh_basis(2, d / norms)  # (K, 9)
    coeffs = basis.T @ c * torch.tensor(KERNEL, dtype=torch.float64)[:, None]
    coeffs[0] += torch.as_tensor(np.asarray(ambient, np.float64)).reshape(3) * UNIFORM_DC
    return coeffs.to(dtype)


@dataclass(frozen=True)
class LightSpec:
    """How a render is lit (module doc): a mode and, for ``given``, the (9, 3) SH irradiance."""

    mode: str = "learned"
    coefficients: tuple | None = None  # 27 floats, row-major (9, 3), for "given"

    def __post_init__(self):
        if self.mode not in LIGHT_MODES:
            raise ValueError(f"light mode must be one of {', '.join(LIGHT_MODES)}, got {self.mode!r}")
        if (self.mode == "given") != (self.coefficients is not None):
            raise ValueError("a 'given' light needs its 27 coefficients, and only it has them")
        if self.coefficients is not None and len(self.coefficients) != 27:
            raise ValueError(f"a given light has 27 SH coefficients (9 x RGB), got {len(self.coefficients)}")

    @classmethod
    def given(cls, coefficients) -> LightSpec:
        values = np.asarray(coefficients, np.float64).reshape(-1)
        if values.size != 27 or not np.isfinite(values).all():
            raise ValueError(f"a given light has 27 finite SH coefficients (9 x RGB), got {values.size}")
        return cls("given", tuple(float(v) for v in values))

    def tensor(self, device=None) -> torch.Tensor:
        return torch.tensor(self.coefficients, dtype=torch.float32, device=device).reshape(SH_BANDS, 3)


def parse_light(text: str | None) -> LightSpec:
    """A LightSpec from a command-line or node parameter value.

    ``learned`` / ``baked`` / ``albedo``; 27 comma-separated numbers (SH irradiance, 9 x RGB,
    row-major); or a JSON file holding ``{"sh": [[r, g, b] x 9]}`` or
    ``{"ambient": [r, g, b], "lights": [{"direction": [x, y, z], "color": [r, g, b]}, ...]}``
    (directions towards the lights, in the dataset's world frame). ValueError says what is wrong.
    """
    if text is None or text == "" or text == "learned":
        return LightSpec()
    if text in ("baked", "albedo"):
        return LightSpec(text)
    if "," in text:
        try:
            values = [float(v) for v in text.split(",")]
        except ValueError:
            raise ValueError(f"--light {text!r}: expected 27 comma-separated numbers") from None
        return LightSpec.given(values)
    path = Path(text)
    if not path.is_file():
        raise ValueError(
            f"--light {text!r}: not learned, baked, albedo, 27 numbers, or an existing JSON file"
        )
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"--light {path}: cannot read it as JSON ({exc})") from exc
    if not isinstance(data, dict):
        raise ValueError(f"--light {path}: expected a JSON object with 'sh' or 'lights'")
    if "sh" in data:
        return LightSpec.given(data["sh"])
    if "lights" in data or "ambient" in data:
        lights = data.get("lights", [])
        try:
            directions = [light["direction"] for light in lights]
            colors = [light["color"] for light in lights]
        except (KeyError, TypeError) as exc:
            raise ValueError(f"--light {path}: every light needs 'direction' and 'color'") from exc
        ambient = data.get("ambient", [0.0, 0.0, 0.0])
        if not lights:
            return LightSpec.given(directional_irradiance(np.zeros((0, 3)), np.zeros((0, 3)), ambient))
        return LightSpec.given(directional_irradiance(directions, colors, ambient))
    raise ValueError(f"--light {path}: expected a JSON object with 'sh' or 'lights'")


def gaussian_normals(
    quats: torch.Tensor, scales: torch.Tensor, means: torch.Tensor, camera_center: torch.Tensor
) -> torch.Tensor:
    """(M, 3) unit world normals: each Gaussian's shortest axis turned by its world rotation
    ``quats`` (M, 4, unit wxyz), flipped to face ``camera_center`` (3,)."""
    axis = torch.zeros_like(scales)
    axis.scatter_(1, scales.detach().argmin(dim=1, keepdim=True), 1.0)
    w, u = quats[:, :1], quats[:, 1:]
    uv = torch.linalg.cross(u, axis)
    normal = axis + 2.0 * (w * uv + torch.linalg.cross(u, uv))  # rotate(quats, axis)
    toward = (camera_center.reshape(1, 3) - means).detach()
    sign = torch.where((normal.detach() * toward).sum(dim=1, keepdim=True) < 0, -1.0, 1.0)
    return normal * sign


def polar_rotation(matrix: np.ndarray) -> np.ndarray:
    """The rotation nearest to ``matrix`` (3, 3) in Frobenius norm (SVD); identity for a zero matrix."""
    u, _, vt = np.linalg.svd(np.asarray(matrix, np.float64))
    if not np.isfinite(u).all():
        return np.eye(3)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return u @ np.diag([1.0, 1.0, d]) @ vt


class Shading(nn.Module):
    """The learned light (8 x 3 learned SH coefficients over a fixed uniform term) and the mean
    training orientation the ``baked`` mode carries it along from."""

    def __init__(self):
        super().__init__()
        self.coefficients = nn.Parameter(torch.zeros(SH_BANDS - 1, 3))  # bands 1 and 2
        self.register_buffer("dc", torch.full((1, 3), UNIFORM_DC))
        self.register_buffer("reference", torch.eye(3))  # mean training root orientation (world)
        self.register_buffer("orientation_sum", torch.zeros(3, 3))  # of the frames seen so far

    def learned(self) -> torch.Tensor:
        """(9, 3) SH irradiance of the learned light."""
        return torch.cat([self.dc, self.coefficients], dim=0)

    def load_learned(self, coefficients: torch.Tensor) -> None:
        with torch.no_grad():
            c = torch.as_tensor(coefficients, dtype=self.dc.dtype, device=self.dc.device).reshape(SH_BANDS, 3)
            self.dc.copy_(c[:1])
            self.coefficients.copy_(c[1:])

    @torch.no_grad()
    def add_orientation(self, root_rotation: torch.Tensor) -> None:
        """Count one training frame's root orientation (3, 3) into the mean the baked mode uses."""
        self.orientation_sum += root_rotation.to(self.orientation_sum)
        mean = polar_rotation(self.orientation_sum.cpu().numpy())
        self.reference.copy_(torch.as_tensor(mean, dtype=self.reference.dtype))

    def penalty(self) -> torch.Tensor:
        """Mean square of the learned (non-uniform) coefficients: zero for uniform light."""
        return self.coefficients.pow(2).mean()

    def forward(
        self,
        albedo: torch.Tensor,
        normals: torch.Tensor,
        light: LightSpec | None = None,
        root_rotation: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Shaded colours (M, 3) of ``albedo`` (M, 3) with world ``normals`` (M, 3) under ``light``.

        ``root_rotation`` (3, 3): the body's world orientation this frame (the ``baked`` mode).
        """
        mode = "learned" if light is None else light.mode
        if mode == "albedo":
            return albedo
        if mode == "given":
            return albedo * irradiance(normals, light.tensor(albedo.device))
        if mode == "baked":
            if root_rotation is None:
                raise ValueError("the baked light needs the body's root orientation")
            # The normal as it would point had the body kept its mean training orientation.
            normals = normals @ root_rotation.to(normals) @ self.reference.T.to(normals)
        return albedo * irradiance(normals, self.learned())
