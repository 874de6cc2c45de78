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


def visibility_many(
    points: torch.Tensor,
    normals: torch.Tensor,
    vertices: torch.Tensor,
    faces: torch.Tensor,
    directions,
    texel_m: float = DEFAULT_TEXEL_M,
) -> torch.Tensor:
    """(K, P) bool: whether a distant light in each of ``directions`` (K, 3; towards the light)
    reaches each of ``points`` (P, 3) with unit ``normals`` (P, 3), past the mesh ``vertices``
    (V, 3) / ``faces`` (F, 3). Points whose normal faces away from a light are not lit by it.

    The K depth maps are tiles of one atlas, rasterized in one call (one call per direction
    spent most of its time in per-call overhead)."""
    dirs = np.asarray(directions, np.float64).reshape(-1, 3)
    verts = vertices.to(torch.float64)
    pts = points.to(torch.float64)
    nrm = normals.to(torch.float64)
    both = torch.cat([verts, pts])
    frames = [_frame(w) for w in dirs]
    d = torch.as_tensor(np.stack([f[0] for f in frames]))  # (K, 3)
    u = torch.as_tensor(np.stack([f[1] for f in frames]))
    v = torch.as_tensor(np.stack([f[2] for f in frames]))
    bu, bv, bd = both @ u.T, both @ v.T, both @ d.T  # (V + P, K)
    lo_u, lo_v = bu.min(dim=0).values, bv.min(dim=0).values
    span = torch.maximum(bu.max(dim=0).values - lo_u, bv.max(dim=0).values - lo_v)
    texel = torch.clamp(span / (MAX_GRID - 4), min=texel_m)  # (K,)
    tile = int(math.ceil(float((span / texel).max()))) + 3  # square tiles, side by side in x
    top = bd.max(dim=0).values + _DEPTH_OFFSET
    k = torch.arange(dirs.shape[0], dtype=torch.float64)

    def screen(x):  # (N, 3) -> (K, N, 2) atlas coordinates, (K, N) depths
        col = (x @ u.T - lo_u) / texel + 1.0 + k * tile
        row = (x @ v.T - lo_v) / texel + 1.0
        return torch.stack([col.T, row.T], dim=2), (top - x @ d.T).T

    xy, depth_v = screen(verts)
    count, nv = dirs.shape[0], verts.shape[0]
    all_faces = (faces.long()[None] + nv * torch.arange(count)[:, None, None]).reshape(-1, 3)
    width = count * tile
    frags = rasterize(xy.reshape(-1, 2), depth_v.reshape(-1), all_faces, tile, width)
    # orthographic depth is affine in the image: from the perspective-correct barycentrics b_i of
    # the nearest triangle, the screen-space ones are b_i z_i / sum b_j z_j, so z = sum b z^2 / sum b z
    z = depth_v.reshape(-1)[all_faces[frags.triangle]]
    b = frags.bary.to(torch.float64)
    zbuffer = torch.full((tile * width,), math.inf, dtype=torch.float64)
    zbuffer[frags.samples] = (b * z * z).sum(1) / (b * z).sum(1)
    # each point moved off its surface by a texel, compared with a slope-scaled bias
    cosine = (nrm @ d.T).T  # (K, P)
    moved = pts[None] + nrm[None] * texel[:, None, None]  # (K, P, 3)
    col = ((moved * u[:, None]).sum(2) - lo_u[:, None]) / texel[:, None] + 1.0
    row = ((moved * v[:, None]).sum(2) - lo_v[:, None]) / texel[:, None] + 1.0
    col = col.round().long().clamp(0, tile - 1) + (k.long() * tile)[:, None]
    row = row.round().long().clamp(0, tile - 1)
    depth = top[:, None] - (moved * d[:, None]).sum(2)
    slope = torch.sqrt((1.0 - cosine.square()).clamp_min(0.0)) / cosine.clamp_min(1e-3)
    bias = texel[:, None] * (1.0 + slope).clamp(max=_MAX_BIAS_TEXELS)
    return (depth <= zbuffer[row * width + col] + bias) & (cosine > 0)


def visibility(
    points: torch.Tensor,
    normals: torch.Tensor,
    vertices: torch.Tensor,
    faces: torch.Tensor,
    direction,
    texel_m: float = DEFAULT_TEXEL_M,
) -> torch.Tensor:
    """(P,) bool: :func:`visibility_many` for one direction."""
    return visibility_many(points, normals, vertices, faces, [direction], texel_m)[0]


def ambient_occlusion(
    points: torch.Tensor,
    normals: torch.Tensor,
    vertices: torch.Tensor,
    faces: torch.Tensor,
    directions: int | np.ndarray = DEFAULT_DIRECTIONS,
    texel_m: float = DEFAULT_TEXEL_M,
    batch: int = 8,
) -> torch.Tensor:
    """(P,) float32 in [0, 1]: the cosine-weighted fraction of each point's hemisphere from which
    the mesh is not seen (1: nothing in the way; module doc). ``directions``: how many (a
    Fibonacci set) or the (K, 3) unit directions themselves; ``batch`` depth maps per atlas."""
    dirs = (
        sphere_directions(directions) if isinstance(directions, int) else np.asarray(directions, np.float64)
    )
    nrm = normals.to(torch.float64)
    lit = torch.zeros(points.shape[0], dtype=torch.float64)
    total = torch.zeros(points.shape[0], dtype=torch.float64)
    for lo in range(0, dirs.shape[0], batch):
        chunk = dirs[lo : lo + batch]
        weight = (nrm @ torch.as_tensor(chunk, dtype=torch.float64).T).clamp_min(0.0)  # (P, k)
        seen = visibility_many(points, normals, vertices, faces, chunk, texel_m)  # (k, P)
        lit += (weight * seen.T).sum(1)
        total += weight.sum(1)
    return torch.where(total > 0, lit / total.clamp_min(1e-12), torch.ones_like(total)).to(torch.float32)
