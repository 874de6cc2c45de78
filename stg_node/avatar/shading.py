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
  rotation). Gaussians start as flat discs along the body surface (``model.init_flatness``) so the
  shortest axis is the surface normal from the start. Its sign: in renders, flipped to face the
  camera (for a surface seen from outside the visible side faces the viewer); in training, with
  ``model.normal_sign = outward`` (chosen by the default ``auto`` where the learned light has
  contrast: normal_trial.py; from the first step flat light is worse with it), the side the disc
  was initialised with (:func:`outward_normals`), so the albedo does not learn to undo the flips
  of the training camera's silhouettes, which a turned body would show; a disc seen from behind
  then teaches the light nothing (``away`` in :meth:`Shading.forward`).
- **Light**, fixed in the world and learned from the training clip with everything else; its
  mean over all directions is held at ``E = 1``, so brightness and colour of the surface stay in
  the albedo and albedo and light cannot trade a common scale. Two models (``model.light_model``):

  * ``distant`` (default, :class:`DistantLights`): an ambient term plus ``model.light_count``
    distant lights, each a non-negative colour and a direction, ``E(n) = a + sum_k c_k max(0,
    n . d_k)`` (normalised). A clip that shows one side of the subject constrains the light only
    through the normals it shows; this model extrapolates to the others as a room does (a surface
    facing away from every light gets the ambient term).
  * ``sh`` (:class:`SHLight`): free second-order spherical-harmonic irradiance (Ramamoorthi and
    Hanrahan 2001), ``E(n) = max(0, sum_k e_k Y_k(n))`` over the 9 real SH functions of
    :func:`color.sh_basis` per channel: 27 numbers, 24 learned. It represents the irradiance of
    any distant light to within a few percent, but fitted on one hemisphere of normals its
    quadratic terms rise again on the other: measured, it lights the side facing away from the
    room's lamp almost as brightly as the lit one (docs/AVATAR.md).

  A small penalty (``loss.light``) keeps the learned light near uniform unless the images ask
  otherwise: a clip that never shows how the light falls leaves the avatar near its baked colour.
  A second one (``loss.light_unseen``) removes what no training view can confirm: a distant
  light that casts more of its light on normals no training camera faces (``Shading.seen``) than
  on those one does (:meth:`DistantLights.unseen_excess`).
  Such a lamp changes the images of the training views only through the normalisation (it
  raises the mean, so it dims every seen normal alike, which the albedo undoes): a direction the
  loss is flat along, which Adam's normalised steps walk. Grown there, it lights the side of the
  subject the clip never showed: measured with SH colour, a lamp straight away from the camera
  rendered the back 2-2.5x too bright (-5.4 dB on novel views; docs/BENCHMARKS.md).

Render modes (:class:`LightSpec`): ``learned`` (the default: the learned light, fixed in the
world, so a turning avatar is lit by the room as it turns), ``given`` (a caller's light: SH
irradiance coefficients, or an ambient term and distant lights, evaluated exactly;
:func:`directional_irradiance` converts the latter to SH), ``baked`` (the learned light carried
along with the body, as if it never turned from its mean training orientation: what a colour
without shading gives, for comparison) and ``albedo`` (no shading: E = 1).

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

from stg_node.avatar import kernels
from stg_node.avatar.color import SH_C0, sh_basis
from stg_node.avatar.config import LIGHT_MODELS
from stg_node.avatar.light_ops import detach_rows, distant_irradiance
from stg_node.avatar.occlusion import BodyOcclusion
from stg_node.splat import shade_ops

SH_BANDS = 9  # second order: l = 0, 1, 2
KERNEL = (math.pi,) + (2.0 * math.pi / 3.0,) * 3 + (math.pi / 4.0,) * 5  # clamped cosine, per coefficient
UNIFORM_DC = 1.0 / SH_C0  # e_00 of E(n) = 1 everywhere
SEEN_DIRECTIONS = 512  # the sphere of normals, Fibonacci lattice: which ones a training view faces
LIGHT_MODES = ("learned", "baked", "albedo", "given")


def sphere_directions(count: int, device=None) -> torch.Tensor:
    """(count, 3) unit directions spread evenly over the sphere (Fibonacci lattice)."""
    i = torch.arange(count, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / count
    r = (1.0 - z * z).sqrt()
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return torch.stack([r * phi.cos(), r * phi.sin(), z], dim=1).float().to(device)


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
    """How a render is lit (module doc). A ``given`` light is SH irradiance (``sh``: 27 floats,
    row-major (9, 3)) or distant lights (``ambient``: RGB, ``lights``: (direction xyz, colour rgb)
    per light, directions towards the lights), evaluated exactly."""

    mode: str = "learned"
    sh: tuple | None = None
    ambient: tuple | None = None
    lights: tuple | None = None

    def __post_init__(self):
        if self.mode not in LIGHT_MODES:
            raise ValueError(f"light mode must be one of {', '.join(LIGHT_MODES)}, got {self.mode!r}")
        given = self.sh is not None or self.ambient is not None
        if (self.mode == "given") != given:
            raise ValueError("a 'given' light needs SH coefficients or lights, and only it has them")
        if self.sh is not None and len(self.sh) != 27:
            raise ValueError(f"a given light has 27 SH coefficients (9 x RGB), got {len(self.sh)}")

    @classmethod
    def given(cls, coefficients) -> LightSpec:
        """A caller's light from SH irradiance coefficients (9, 3)."""
        values = np.asarray(coefficients, np.float64).reshape(-1)
        if values.size != 27 or not np.isfinite(values).all():
            raise ValueError(f"a given light has 27 finite SH coefficients (9 x RGB), got {values.size}")
        return cls("given", sh=tuple(float(v) for v in values))

    @classmethod
    def distant(cls, ambient, directions=(), colors=()) -> LightSpec:
        """A caller's light: an ambient term plus distant lights (``ambient + sum c_k max(0, n.d_k)``)."""
        a = np.asarray(ambient, np.float64).reshape(3)
        d = np.asarray(directions, np.float64).reshape(-1, 3)
        c = np.asarray(colors, np.float64).reshape(-1, 3)
        if d.shape[0] != c.shape[0]:
            raise ValueError(f"{d.shape[0]} light directions but {c.shape[0]} colours")
        norms = np.linalg.norm(d, axis=1, keepdims=True)
        if (
            not (np.isfinite(a).all() and np.isfinite(d).all() and np.isfinite(c).all())
            or (norms < 1e-9).any()
        ):
            raise ValueError("light directions must be finite and non-zero, colours finite")
        rows = tuple(tuple(float(v) for v in row) for row in np.concatenate([d / norms, c], axis=1))
        return cls("given", ambient=tuple(float(v) for v in a), lights=rows)

    def tensor(self, device=None) -> torch.Tensor:
        """(9, 3) SH irradiance of a given light (distant lights converted: directional_irradiance)."""
        if self.sh is not None:
            return torch.tensor(self.sh, dtype=torch.float32, device=device).reshape(SH_BANDS, 3)
        rows = np.asarray(self.lights or np.zeros((0, 6)), np.float64).reshape(-1, 6)
        return directional_irradiance(rows[:, :3], rows[:, 3:], self.ambient).to(device)

    def irradiance(self, normals: torch.Tensor) -> torch.Tensor:
        """(M, 3) irradiance of a given light at world ``normals`` (M, 3)."""
        if self.sh is not None:
            return irradiance(normals, self.tensor(normals.device))
        out = torch.tensor(self.ambient, dtype=normals.dtype, device=normals.device).expand(
            normals.shape[0], 3
        )
        if self.lights:
            rows = torch.tensor(self.lights, dtype=normals.dtype, device=normals.device)
            out = out + (normals @ rows[:, :3].T).clamp_min(0.0) @ rows[:, 3:]
        return out


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
        return LightSpec.distant(data.get("ambient", [0.0, 0.0, 0.0]), directions, colors)
    raise ValueError(f"--light {path}: expected a JSON object with 'sh' or 'lights'")


def gaussian_normals(
    quats: torch.Tensor,
    scales: torch.Tensor,
    means: torch.Tensor,
    camera_center: torch.Tensor,
    outward: bool = False,
) -> torch.Tensor:
    """(M, 3) unit world normals: each Gaussian's shortest axis turned by its world rotation
    ``quats`` (M, 4, unit wxyz), flipped to face ``camera_center`` (3,). Where the kernels run,
    the fused kernel (stg_node.splat.skin_ops.gaussian_normals: the same operations in one pass,
    equal to float rounding, its backward written out); the gradient reaches ``quats`` only (the
    axis and the sign are constants for it).

    ``outward``: a Gaussian whose shortest axis is its local z axis keeps that axis's sign (the
    disc initialisation points it out of the body: :func:`outward_normals`); the others are
    flipped to face the camera as above."""
    if outward:
        return outward_normals(quats, scales, means, camera_center)
    if kernels.use_kernels(quats, scales, means, camera_center):
        from stg_node.splat import skin_ops

        return skin_ops.gaussian_normals(quats, scales, means, camera_center)
    normal = shortest_axes(quats, scales)
    toward = (camera_center.reshape(1, 3) - means).detach()
    sign = torch.where((normal.detach() * toward).sum(dim=1, keepdim=True) < 0, -1.0, 1.0)
    return normal * sign


def outward_normals(
    quats: torch.Tensor, scales: torch.Tensor, means: torch.Tensor, camera_center: torch.Tensor
) -> torch.Tensor:
    """(M, 3) unit world normals signed by the body rather than by the camera.

    A disc initialised on the body surface (``model.init_flatness`` < 1, gaussians.new_columns)
    has its local +z axis along the surface's outward normal, and learning turns it continuously:
    while z stays the shortest axis, +z is where the surface faces. Flipping every normal towards
    the camera instead gives a Gaussian at a silhouette (its normal nearly across the line of
    sight) a sign that depends on the viewer, and the shade of the side facing away from the light:
    the albedo learns to undo that for the training camera and orientation only, and a turned body
    shows it (docs/AVATAR.md, "Which way a normal points"). Gaussians whose shortest axis is
    another one (re-sampled spheres, a disc that grew thin along x or y) have no side of their
    own and are flipped to face the camera."""
    normal = shortest_axes(quats, scales)
    shortest = scales.detach().argmin(dim=1, keepdim=True)
    toward = (camera_center.reshape(1, 3) - means).detach()
    facing = (normal.detach() * toward).sum(dim=1, keepdim=True) >= 0
    sign = torch.where((shortest == 2) | facing, 1.0, -1.0).to(normal.dtype)
    return normal * sign


def shortest_axes(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """(M, 3) unit shortest axis of each Gaussian (rotation ``quats`` (M, 4, unit wxyz), ``scales``
    (M, 3)) in the frame of its rotation, without a sign of its own."""
    axis = torch.zeros_like(scales)
    axis.scatter_(1, scales.detach().argmin(dim=1, keepdim=True), 1.0)
    w, u = quats[:, :1], quats[:, 1:]
    uv = torch.linalg.cross(u, axis)
    return axis + 2.0 * (w * uv + torch.linalg.cross(u, uv))  # rotate(quats, axis)


def polar_rotation(matrix: np.ndarray) -> np.ndarray:
    """The rotation nearest to ``matrix`` (3, 3) in Frobenius norm (SVD); identity for a zero matrix."""
    u, _, vt = np.linalg.svd(np.asarray(matrix, np.float64))
    if not np.isfinite(u).all():
        return np.eye(3)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return u @ np.diag([1.0, 1.0, d]) @ vt


class SHLight(nn.Module):
    """Learned second-order SH irradiance: 8 x 3 free coefficients over a constant term fixed at E = 1."""

    def __init__(self):
        super().__init__()
        self.coefficients = nn.Parameter(torch.zeros(SH_BANDS - 1, 3))  # bands 1 and 2
        self.register_buffer("dc", torch.full((1, 3), UNIFORM_DC))

    def sh(self) -> torch.Tensor:
        return torch.cat([self.dc, self.coefficients], dim=0)

    def irradiance(self, normals: torch.Tensor, away: torch.Tensor | None = None) -> torch.Tensor:
        return detach_rows(irradiance(normals, self.sh()), away)

    def penalty(self) -> torch.Tensor:
        """Mean square of the non-constant coefficients: zero for uniform light."""
        return self.coefficients.pow(2).mean()


INITIAL_DIRECTIONS = ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 1.0, 0.0))


class DistantLights(nn.Module):
    """Learned light as a room has it: an ambient term and ``count`` distant lights, per channel

        E(n) = (a + sum_k c_k max(0, n . d_k)) / (a + sum_k c_k / 4)

    with ``a, c_k >= 0`` (softplus) and unit directions ``d_k``. The denominator is the mean of the
    numerator over all directions, so E averages 1 (as SHLight's constant term) and the albedo keeps
    the surface's brightness. Unlike free SH coefficients, this cannot brighten a side no light
    faces: fitted from the normals a clip shows, it extrapolates to the others as a room would (a
    surface facing away from every light gets the ambient term), where a second-order polynomial
    fitted on one hemisphere rises again on the other. Starts uniform (weak lights, E ~ 1).
    """

    def __init__(self, count: int):
        super().__init__()
        if not 1 <= count <= len(INITIAL_DIRECTIONS):
            raise ValueError(f"light_count must be 1..{len(INITIAL_DIRECTIONS)}, got {count}")
        self.ambient = nn.Parameter(torch.full((3,), math.log(math.e - 1.0)))  # softplus -> 1
        self.colors = nn.Parameter(torch.full((count, 3), -3.0))  # softplus -> 0.05: weak
        self.directions = nn.Parameter(torch.tensor(INITIAL_DIRECTIONS[:count]))

    def parts(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(ambient (3,), colours (K, 3), unit directions (K, 3), mean irradiance (3,)), unnormalised."""
        a = torch.nn.functional.softplus(self.ambient)
        c = torch.nn.functional.softplus(self.colors)
        d = self.directions / self.directions.norm(dim=1, keepdim=True).clamp_min(1e-9)
        return a, c, d, a + c.sum(dim=0) / 4.0

    def irradiance(self, normals: torch.Tensor, away: torch.Tensor | None = None) -> torch.Tensor:
        """(M, 3) the light each normal (M, 3) receives; rows where ``away`` (M,) bool is set pass
        no gradient (light_ops: one autograd node)."""
        a, c, d, mean = self.parts()
        return distant_irradiance(normals, a, c, d, mean, away)

    def sh(self) -> torch.Tensor:
        """(9, 3) the same light as SH irradiance (second order: to about 3 % of its lobes)."""
        with torch.no_grad():
            a, c, d, mean = self.parts()
            return directional_irradiance(d.cpu().numpy(), (c / mean).cpu().numpy(), (a / mean).cpu().numpy())

    def penalty(self) -> torch.Tensor:
        """Mean square of the share of the mean irradiance the distant lights bring: 0 for ambient only."""
        _, c, _, mean = self.parts()
        return ((c.sum(dim=0) / 4.0) / mean).pow(2).mean()

    def unseen_excess(self, directions: torch.Tensor, seen: torch.Tensor) -> torch.Tensor:
        """The share of the mean irradiance cast by lights that light unseen normals more than seen
        ones, by that excess (mean over RGB).

        With ``u_k`` the part of light k's lobe ``max(0, n . d_k)`` that falls on ``directions``
        (D, 3) whose ``seen`` (D,) is 0, light k pays its share of the mean, ``c_k / 4 / mean``,
        times ``max(0, u_k - (1 - u_k))``: nothing while at least half its light falls where a
        training view looked (a light from the side, whose direction the images fix: a linear
        charge on ``u_k`` tilted the benchmark's room lamp 10 degrees towards the camera and cost
        its held-out turn 0.5 dB), its whole share when it faces only unseen normals."""
        _, c, d, mean = self.parts()
        lobe = torch.relu(directions @ d.T)  # (D, K)
        unseen = (lobe * (1.0 - seen)[:, None]).sum(0) / lobe.sum(0).clamp_min(1e-9)  # (K,)
        return ((c / 4.0 / mean) * torch.relu(2.0 * unseen - 1.0)[:, None]).sum(0).mean()


class Shading(nn.Module):
    """The learned light (``light_model``: ``distant`` lights or ``sh``) and the mean training
    orientation the ``baked`` mode carries it along from; with ``occlusion``, what the body casts
    on itself (occlusion.BodyOcclusion: its spheres are fitted by the trainer)."""

    def __init__(self, light_model: str = "distant", light_count: int = 2, occlusion: bool = False):
        super().__init__()
        if light_model not in LIGHT_MODELS:
            raise ValueError(f"light_model must be one of {', '.join(LIGHT_MODELS)}, got {light_model!r}")
        self.light = DistantLights(light_count) if light_model == "distant" else SHLight()
        self.occlusion = BodyOcclusion() if occlusion else None
        self.register_buffer("reference", torch.eye(3))  # mean training root orientation (world)
        self.register_buffer("orientation_sum", torch.zeros(3, 3))  # of the frames seen so far
        # Which normals (of SEEN_DIRECTIONS, world frame) some training view faces (add_view):
        # 1 seen, 0 not. A snapshot from before it loads with all seen (no unseen penalty).
        self.register_buffer("seen", torch.zeros(SEEN_DIRECTIONS))
        # Their directions, made once (the penalty reads them every step); not saved: derived.
        self.register_buffer("lattice", sphere_directions(SEEN_DIRECTIONS), persistent=False)

    def learned_sh(self) -> torch.Tensor:
        """(9, 3) the learned light as SH irradiance (what stg-render --light takes back)."""
        return self.light.sh().detach()

    @torch.no_grad()
    def add_orientation(self, root_rotation: torch.Tensor) -> None:
        """Count one training frame's root orientation (3, 3) into the mean the baked mode uses."""
        self.orientation_sum += root_rotation.to(self.orientation_sum)
        mean = polar_rotation(self.orientation_sum.cpu().numpy())
        self.reference.copy_(torch.as_tensor(mean, dtype=self.reference.dtype))

    @torch.no_grad()
    def add_view(self, towards_camera: torch.Tensor) -> None:
        """Count the normals a training view faces: those within 90 degrees of the direction (3,)
        from the subject to its camera (world frame)."""
        v = towards_camera.to(self.seen) / towards_camera.norm().clamp_min(1e-9)
        self.seen[self.lattice @ v > 0.0] = 1.0

    def seen_at(self, directions: torch.Tensor) -> torch.Tensor:
        """(M,) bool: whether each unit direction (M, 3) is seen (that of its nearest lattice point)."""
        return self.seen[(directions.to(self.lattice) @ self.lattice.T).argmax(dim=1)] > 0.5

    def penalty(self) -> torch.Tensor:
        return self.light.penalty()

    def unseen_penalty(self) -> torch.Tensor | None:
        """The light cast mostly where no training view looked (distant lights; None for SH light,
        whose lobes are not separable by direction)."""
        if not isinstance(self.light, DistantLights):
            return None
        return self.light.unseen_excess(self.lattice, self.seen)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        if prefix + "seen" not in state_dict:  # saved before the buffer existed: everything seen
            state_dict[prefix + "seen"] = torch.ones(SEEN_DIRECTIONS)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def _fused(self, albedo, normals, visible) -> bool:
        """Whether the learned distant lights shade these rows in the kernel (splat.shade_ops: the
        torch ops below are its reference, ``STG_AVATAR_KERNELS=torch``)."""
        if not isinstance(self.light, DistantLights) or self.light.colors.shape[0] > shade_ops.MAX_LIGHTS:
            return False
        if visible is not None and visible.requires_grad:
            return False
        return kernels.use_kernels(albedo, normals, visible, *self.light.parameters())

    def forward(
        self,
        albedo: torch.Tensor,
        normals: torch.Tensor,
        light: LightSpec | None = None,
        root_rotation: torch.Tensor | None = None,
        visible: torch.Tensor | None = None,
        away: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Shaded colours (M, 3) of ``albedo`` (M, 3) with world ``normals`` (M, 3) under ``light``.

        ``root_rotation`` (3, 3): the body's world orientation this frame (the ``baked`` mode).
        ``visible`` (M,): the share of each Gaussian's sky the body leaves open (occlusion.py).
        ``away`` (M,) bool: rows whose normal faces away from the camera (training with outward
        normals): their shade passes no gradient to the light or to their normals.
        """
        mode = "learned" if light is None else light.mode
        if mode == "albedo":
            return albedo
        if visible is not None and self.occlusion is None:
            visible = None  # no occlusion term to weigh it
        if mode == "baked":
            if root_rotation is None:
                raise ValueError("the baked light needs the body's root orientation")
            # The normal as it would point had the body kept its mean training orientation.
            normals = normals @ root_rotation.to(normals) @ self.reference.T.to(normals)
        if mode != "given" and self._fused(albedo, normals, visible):  # one pass, forward and backward
            logit = None if visible is None else self.occlusion.strength_logit
            lights = self.light
            return shade_ops.shade(
                albedo, normals, visible, logit, lights.ambient, lights.colors, lights.directions, away
            )
        if visible is not None:
            albedo = albedo * self.occlusion.factor(visible)
        if mode == "given":
            return albedo * light.irradiance(normals)
        light = self.light.irradiance(normals, away)  # away: its shade teaches the light nothing
        return albedo * light
