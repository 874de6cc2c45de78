"""What the posed body casts on itself: ambient occlusion and shadows of distant lights.

Without it the benchmark's subject is lit as if its limbs were transparent to light: an arm held
in front of the chest leaves the chest as bright as in any other pose, and no avatar could show
that modelling the body's self-occlusion pays. With ``stg-synth --self-shadow`` each vertex of the
posed surface (garment included) gets

- an **ambient occlusion** ``A``: the cosine-weighted fraction of its hemisphere (around the
  vertex normal) from which no part of the body is seen, ``A = (1/pi) int V(w) max(0, n . w) dw``,
  which multiplies the light that comes from everywhere (the ambient term and the sky);
- a **shadow** ``V_k`` per distant light: 1 where the light reaches the vertex, 0 where the body
  is in the way, which multiplies that light's term.

How (the depth-map method of shadow mapping, applied in many directions): for each direction
``w`` of a Fibonacci set over the sphere the surface is rasterized orthographically along ``w``
(``mesh_raster.rasterize``: z-buffered triangles) into a grid of ``texel_m`` texels; a point is
lit from ``w`` when nothing in the depth map lies between it and the light (it is moved along its
normal by a texel first, and compared with a slope-scaled bias of a texel or more, so the surface
does not shadow itself). ``A`` is the quadrature ``sum_k c_k V_k / sum_k c_k`` over the set's
directions, ``c_k = max(0, n . w_k)``. Tested against the closed-form form factor of a wall
(docs/SYNTH.md). Cost: one small rasterization per direction per frame (the timing is in
docs/SYNTH.md).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from stg_node.data.synth.mesh_raster import rasterize

DEFAULT_DIRECTIONS = 32
DEFAULT_TEXEL_M = 0.02
MAX_GRID = 1024  # texels per side at most (a larger scene gets coarser texels)
# metres in front of the nearest point: depths stay positive, and the rasterizer's perspective-correct
# (harmonic) interpolation, which only picks the nearest triangle here, stays near-linear
_DEPTH_OFFSET = 100.0
_MAX_BIAS_TEXELS = 4.0


def sphere_directions(count: int) -> np.ndarray:
    """(count, 3) unit directions spread evenly over the sphere (Fibonacci lattice)."""
    if count < 1:
        raise ValueError(f"need at least one direction, got {count}")
    k = np.arange(count, dtype=np.float64) + 0.5
    z = 1.0 - 2.0 * k / count
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _frame(direction: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit ``d`` and two unit axes ``u, v`` orthogonal to it."""
    d = np.asarray(direction, np.float64).reshape(3)
    d = d / np.linalg.norm(d)
    helper = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(d, helper)
    u /= np.linalg.norm(u)
    return d, u, np.cross(d, u)


def visibility(
    points: torch.Tensor,
    normals: torch.Tensor,
    vertices: torch.Tensor,
    faces: torch.Tensor,
    direction,
    texel_m: float = DEFAULT_TEXEL_M,
) -> torch.Tensor:
    """(P,) bool: whether a distant light in ``direction`` (towards the light) reaches each of
    ``points`` (P, 3) with unit ``normals`` (P, 3), past the mesh ``vertices`` (V, 3) / ``faces``
    (F, 3). Points whose normal faces away from the light are not lit (False)."""
    d, u, v = (torch.as_tensor(a, dtype=torch.float64) for a in _frame(direction))
    verts = vertices.to(torch.float64)
    pts = points.to(torch.float64)
    nrm = normals.to(torch.float64)
    cosine = nrm @ d
    both = torch.cat([verts, pts])
    lo_u, hi_u = float((both @ u).min()), float((both @ u).max())
    lo_v, hi_v = float((both @ v).min()), float((both @ v).max())
    texel = max(texel_m, (hi_u - lo_u) / (MAX_GRID - 4), (hi_v - lo_v) / (MAX_GRID - 4))
    width = int(math.ceil((hi_u - lo_u) / texel)) + 3
    height = int(math.ceil((hi_v - lo_v) / texel)) + 3
    top = float((both @ d).max()) + _DEPTH_OFFSET

    def screen(x):
        return torch.stack([(x @ u - lo_u) / texel + 1.0, (x @ v - lo_v) / texel + 1.0], dim=1)

    depth_v = top - verts @ d
    frags = rasterize(screen(verts), depth_v, faces, height, width)
    # orthographic depth is affine in the image: from the perspective-correct barycentrics b_i of
    # the nearest triangle, the screen-space ones are b_i z_i / sum b_j z_j, so z = sum b z^2 / sum b z
    z = depth_v[faces.long()[frags.triangle]]
    b = frags.bary.to(torch.float64)
    zbuffer = torch.full((height * width,), math.inf, dtype=torch.float64)
    zbuffer[frags.samples] = (b * z * z).sum(1) / (b * z).sum(1)
    # the point moved off its surface by a texel, compared with a slope-scaled bias
    moved = pts + nrm * texel
    xy = screen(moved).round().long()
    col = xy[:, 0].clamp(0, width - 1)
    row = xy[:, 1].clamp(0, height - 1)
    depth = top - moved @ d
    slope = torch.sqrt((1.0 - cosine.square()).clamp_min(0.0)) / cosine.clamp_min(1e-3)
    bias = texel * (1.0 + slope).clamp(max=_MAX_BIAS_TEXELS)
    return (depth <= zbuffer[row * width + col] + bias) & (cosine > 0)


def ambient_occlusion(
    points: torch.Tensor,
    normals: torch.Tensor,
    vertices: torch.Tensor,
    faces: torch.Tensor,
    directions: int | np.ndarray = DEFAULT_DIRECTIONS,
    texel_m: float = DEFAULT_TEXEL_M,
) -> torch.Tensor:
    """(P,) float32 in [0, 1]: the cosine-weighted fraction of each point's hemisphere from which
    the mesh is not seen (1: nothing in the way; module doc). ``directions``: how many (a
    Fibonacci set) or the (K, 3) unit directions themselves."""
    dirs = (
        sphere_directions(directions) if isinstance(directions, int) else np.asarray(directions, np.float64)
    )
    nrm = normals.to(torch.float64)
    lit = torch.zeros(points.shape[0], dtype=torch.float64)
    total = torch.zeros(points.shape[0], dtype=torch.float64)
    for w in dirs:
        weight = (nrm @ torch.as_tensor(w, dtype=torch.float64)).clamp_min(0.0)
        if not bool((weight > 0).any()):
            continue
        seen = visibility(points, normals, vertices, faces, w, texel_m)
        lit += weight * seen
        total += weight
    return torch.where(total > 0, lit / total.clamp_min(1e-12), torch.ones_like(total)).to(torch.float32)
