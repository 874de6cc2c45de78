"""How the synthetic benchmark's subject is lit: no light, a light that turns with the body, a light
fixed in the room, or an environment of several lights.

Every mode is Lambertian: a vertex's shade is ``ambient + sum_k colour_k max(0, n . l_k)`` with
``n`` the unit normal of the deformed surface (garment included) and ``l_k`` the direction
towards light ``k``; the texture's albedo is multiplied by it (Gouraud). What differs is where
the lights are:

- ``none``: the albedo alone (flat light); nothing to learn about light.
- ``lambert``: one directional light fixed in the body's root frame (from its upper left front):
  turning the whole body does not change its shading, bending a limb does. Today's default,
  kept for comparisons with earlier runs; a real light does not follow the subject.
- ``room``: one directional light fixed in the world (the room), from the upper left of a
  subject facing the training camera and more from the side than ``lambert``'s, plus a weaker
  ambient term. A subject that turns presents other sides to it: a side that faced the light in
  training may face away from it in a held-out pose.
- ``environment``: three coloured directional lights fixed in the world (a warm key from the
  upper left front, a cool fill from the right, a rim light from behind and above) over a sky
  ambient that is brighter on surfaces facing up: a lit room rather than one lamp.

Lights are distant (directional): the same at every point of the body, as the low-order
spherical-harmonic lighting the avatar learns assumes. By default the body does not shadow
itself; with ``self_shadow`` (``stg-synth --self-shadow``, :mod:`occlusion`) the ambient term and
the sky are multiplied by each vertex's ambient occlusion from the posed body and every light's
term by whether the body is in its way.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from stg_node.data.synth.mesh_raster import vertex_normals
from stg_node.data.synth.occlusion import ambient_occlusion, visibility
from stg_node.data.synth.rotations import axis_angle_to_matrix

SHADING_MODES = ("lambert", "none", "room", "environment")


def _unit(v) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=np.float64)
    return tuple(float(x) for x in a / np.linalg.norm(a))


# In SMPL axes (x = the subject's left, y up, z front): from the subject's upper left front.
LIGHT_DIRECTION_BODY = np.array(_unit([0.35, 0.55, 0.75]))
AMBIENT = 0.45
DIFFUSE = 0.55
# The room's key light, in the world (z up, the training camera on -y): from the upper left of a
# subject facing the camera, more from the side than ``lambert``'s, so that a turned subject shows
# its lit side on the other side of the training camera's image.
ROOM_LIGHT_DIRECTION = _unit([0.75, -0.4, 0.5])


@dataclass(frozen=True)
class DirectionalLight:
    """A distant light: ``direction`` (unit, towards the light), RGB ``color`` (intensity), and
    the frame the direction is given in: ``world`` (fixed in the room) or ``body`` (SMPL root axes)."""

    direction: tuple[float, float, float]
    color: tuple[float, float, float]
    frame: str = "world"

    def to_dict(self) -> dict:
        return {"direction": list(self.direction), "color": list(self.color), "frame": self.frame}


@dataclass(frozen=True)
class Lighting:
    """Ambient term plus directional lights; ``sky`` adds ``sky * n_z`` to the ambient (world up)."""

    mode: str
    ambient: tuple[float, float, float] = (0.0, 0.0, 0.0)
    lights: tuple[DirectionalLight, ...] = ()
    sky: float = 0.0

    @property
    def lit(self) -> bool:
        return self.mode != "none"

    @property
    def coloured(self) -> bool:
        """Whether the shade differs between colour channels (then it is (V, 3), else (V,))."""
        colours = [self.ambient] + [light.color for light in self.lights]
        return any(len(set(c)) > 1 for c in colours)

    def world_directions(self, Rh: np.ndarray) -> list[np.ndarray]:
        """Each light's direction in the world for a body whose global rotation is ``Rh`` (3,)."""
        root = axis_angle_to_matrix(np.asarray(Rh, dtype=np.float64).reshape(3))
        return [
            root @ np.asarray(light.direction) if light.frame == "body" else np.asarray(light.direction)
            for light in self.lights
        ]

    def vertex_shade(
        self, vertices: torch.Tensor, faces: torch.Tensor, Rh: np.ndarray, self_shadow: bool = False
    ) -> torch.Tensor | None:
        """Per-vertex shade (V,) or (V, 3) of the deformed surface ``vertices`` (V, 3); None when unlit.

        ``self_shadow``: the body occludes itself (ambient occlusion on the ambient term and the
        sky, a shadow on each light: :mod:`occlusion`)."""
        if not self.lit:
            return None
        normals = vertex_normals(vertices, faces)
        channels = 3 if self.coloured else 1
        shade = torch.zeros(normals.shape[0], channels, dtype=torch.float32)
        shade += torch.as_tensor(self.ambient[:channels], dtype=torch.float32)
        if self.sky:
            shade += self.sky * normals[:, 2:3]
        if self_shadow:
            shade *= ambient_occlusion(vertices, normals, vertices, faces)[:, None]
        for light, direction in zip(self.lights, self.world_directions(Rh), strict=True):
            cosine = (normals @ torch.as_tensor(direction, dtype=torch.float32)).clamp(min=0.0)
            if self_shadow:
                cosine = cosine * visibility(vertices, normals, vertices, faces, direction)
            shade += cosine[:, None] * torch.as_tensor(light.color[:channels], dtype=torch.float32)
        return shade[:, 0] if channels == 1 else shade

    def to_dict(self) -> dict:
        return {
            "mode": self.mode,
            "ambient": list(self.ambient),
            "sky": self.sky,
            "lights": [light.to_dict() for light in self.lights],
        }


def lighting(mode: str) -> Lighting:
    """The lighting of shading mode ``mode`` (one of :data:`SHADING_MODES`)."""
    if mode == "none":
        return Lighting("none")
    if mode == "lambert":
        return Lighting(
            "lambert",
            (AMBIENT,) * 3,
            (DirectionalLight(tuple(LIGHT_DIRECTION_BODY), (DIFFUSE,) * 3, "body"),),
        )
    if mode == "room":
        return Lighting("room", (0.3,) * 3, (DirectionalLight(ROOM_LIGHT_DIRECTION, (0.7,) * 3),))
    if mode == "environment":
        return Lighting(
            "environment",
            (0.2, 0.2, 0.22),
            (
                DirectionalLight(ROOM_LIGHT_DIRECTION, (0.55, 0.48, 0.4)),  # warm key
                DirectionalLight(_unit([-0.85, -0.25, 0.3]), (0.2, 0.25, 0.32)),  # cool fill, right
                DirectionalLight(_unit([0.1, 0.8, 0.6]), (0.3, 0.3, 0.33)),  # rim, behind and above
            ),
            sky=0.06,
        )
    raise ValueError(f"unknown shading {mode!r}; choose one of {', '.join(SHADING_MODES)}")
