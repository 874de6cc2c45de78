"""An independent z-buffered, textured triangle rasterizer: the synthetic benchmark's ground truth.

Why a second renderer: the benchmark's images must never come from our Gaussian splatter,
or a splatter bug would hide in the ground truth. This is a classic mesh rasterizer in
vectorised torch (CPU), written from the textbook definitions and tested against closed forms.

Conventions
- Cameras: OpenCV pinhole (x right, y down, z forward), world-to-camera ``R``, ``t``,
  intrinsics ``K``. Pixel (row r, column c) has its centre at image coordinates (c, r),
  the convention ``K`` is written in. With ``supersample=s`` the pixel holds s x s samples
  at ``(c - 1/2 + (j + 1/2)/s, r - 1/2 + (i + 1/2)/s)``.
- Coverage: a sample is covered by a triangle when all three barycentrics are >= -1e-6
  (edges inclusive, so meshes never crack; a sample on a shared edge is claimed by both
  and the depth test decides). Degenerate triangles and triangles with a vertex closer than
  ``near`` to the camera plane are dropped (no clipping: the benchmark's cameras are metres
  away). Optional back-face culling keeps triangles that are counter-clockwise seen from
  the camera (outward normals of a mesh with counter-clockwise outward faces, as SMPL's).
- Depth test: the smallest camera-space z wins; exact ties go to the lower triangle index,
  so the result never depends on evaluation order.
- Interpolation is perspective-correct: with screen-space barycentrics ``l_i`` and vertex
  depths ``z_i``, the weights are ``(l_i / z_i) / sum_j (l_j / z_j)`` and the depth is
  ``1 / sum_j (l_j / z_j)``.
- Textures: bilinear, clamp-to-edge, texel centres at half-integers; ``uv = (0, 0)`` is the
  bottom-left corner of the texture image (OBJ / OpenGL convention), ``v`` grows upwards.
- Anti-aliasing: supersampling; the colour of a pixel is the mean of its samples over a
  black background, the coverage is the fraction of covered samples, the mask is
  ``coverage >= 1/2`` and pixels outside the mask are set to black, so image and mask agree.

Algorithm: each triangle's bounding box is enumerated in buckets of similar size
(power-of-two widths and heights), the covered (sample, triangle) pairs are packed into
int64 keys ``(float32 depth bits << 32) | triangle`` and reduced per sample with
``scatter_reduce(amin)``: one pass gives the z-buffer and the visible triangle.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from stg_node.data.types import Camera

INSIDE_EPS = 1e-6
DEFAULT_NEAR = 1e-3
_EMPTY_KEY = torch.iinfo(torch.int64).max
_TRI_BITS = 32
_TRI_MASK = (1 << _TRI_BITS) - 1
# Upper bound on the (triangle, sample) pairs materialised at once (memory ~ 40 bytes each).
DEFAULT_MAX_PAIRS = 1 << 21


@dataclass
class Fragments:
    """The covered samples of a ``height`` x ``width`` sample grid, in row-major order.

    Only covered samples are stored: at 1024 x 1024 samples a body covers a fifth of the
    grid, and dense per-sample buffers would cost more than the rasterization itself.
    """

    samples: torch.Tensor  # (N,) int64 flat sample index row * width + column, ascending
    triangle: torch.Tensor  # (N,) int64 visible triangle
    bary: torch.Tensor  # (N, 3) float32 perspective-correct barycentrics
    depth: torch.Tensor  # (N,) float32 camera-space z
    height: int
    width: int

    def dense_triangle(self) -> torch.Tensor:
        """(height, width) int64 visible triangle per sample, -1 where empty."""
        out = torch.full((self.height * self.width,), -1, dtype=torch.int64)
        out[self.samples] = self.triangle
        return out.reshape(self.height, self.width)

    def dense_depth(self) -> torch.Tensor:
        """(height, width) float32 camera-space z per sample, 0 where empty."""
        out = torch.zeros(self.height * self.width, dtype=torch.float32)
        out[self.samples] = self.depth
        return out.reshape(self.height, self.width)


@dataclass
class RenderResult:
    """A rendered view at the output resolution."""

    image: np.ndarray  # (H, W, 3) uint8 RGB, black outside the mask
    mask: np.ndarray  # (H, W) uint8, 255 on the mesh
    coverage: np.ndarray  # (H, W) float32 fraction of covered samples in [0, 1]
    depth: np.ndarray  # (H, W) float32 mean camera-space z of the covered samples (0 = background)


def supersampled_intrinsics(K: np.ndarray | torch.Tensor, supersample: int) -> torch.Tensor:
    """Intrinsics of the s-times denser sample grid (sample (i, j) of pixel (r, c) as in the module doc)."""
    K = torch.as_tensor(K, dtype=torch.float64)
    s = float(supersample)
    scaled = K.clone()
    scaled[0, :] *= s
    scaled[1, :] *= s
    scaled[0, 2] += (s - 1.0) / 2.0
    scaled[1, 2] += (s - 1.0) / 2.0
    return scaled


def project_points(
    points_world: torch.Tensor, K: torch.Tensor, R: torch.Tensor, t: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """World points (V, 3) -> image coordinates (V, 2) and camera-space depth (V,), in float64."""
    pts = points_world.to(torch.float64)
    cam = pts @ torch.as_tensor(R, dtype=torch.float64).T + torch.as_tensor(t, dtype=torch.float64)
    z = cam[:, 2]
    safe = torch.where(z.abs() > 1e-12, z, torch.ones_like(z))
    K = torch.as_tensor(K, dtype=torch.float64)
    x = K[0, 0] * cam[:, 0] / safe + K[0, 1] * cam[:, 1] / safe + K[0, 2]
    y = K[1, 1] * cam[:, 1] / safe + K[1, 2]
    return torch.stack([x, y], dim=1), z


def _ceil_pow2_exponent(n: torch.Tensor) -> torch.Tensor:
    """Smallest e with 2**e >= n, for n >= 1 (int64)."""
    e = torch.zeros_like(n)
    while True:
        small = (1 << e) < n
        if not bool(small.any()):
            return e
        e = e + small.to(e.dtype)


def rasterize(
    screen_xy: torch.Tensor,
    depth: torch.Tensor,
    faces: torch.Tensor,
    height: int,
    width: int,
    *,
    cull_backfaces: bool = False,
    near: float = DEFAULT_NEAR,
    max_pairs: int = DEFAULT_MAX_PAIRS,
) -> Fragments:
    """Z-buffered coverage of triangles ``faces`` (F, 3) of vertices at ``screen_xy`` (V, 2), ``depth`` (V,).

    Sample (row r, column c) is the point (c, r) of the image plane. Returns the visible
    triangle, perspective-correct barycentrics and depth of every covered sample.
    """
    if screen_xy.ndim != 2 or screen_xy.shape[1] != 2:
        raise ValueError(f"screen_xy must be (V, 2), got {tuple(screen_xy.shape)}")
    if depth.shape != screen_xy.shape[:1]:
        raise ValueError(f"depth must be (V,) = ({screen_xy.shape[0]},), got {tuple(depth.shape)}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must be (F, 3), got {tuple(faces.shape)}")
    if height < 1 or width < 1:
        raise ValueError(f"sample grid must be positive, got {height} x {width}")
    faces = faces.to(torch.int64)
    xy = screen_xy.to(torch.float64)
    z = depth.to(torch.float64)

    # --- per-triangle setup (float64) ---------------------------------------------------
    corners = [faces[:, i].contiguous() for i in range(3)]
    x_col, y_col = xy[:, 0].contiguous(), xy[:, 1].contiguous()
    x0, x1, x2 = (_take(x_col, f) for f in corners)
    y0, y1, y2 = (_take(y_col, f) for f in corners)
    area2 = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
    vertex_ok = (z > near) & torch.isfinite(xy[:, 0]) & torch.isfinite(xy[:, 1])
    keep = vertex_ok[faces[:, 0]] & vertex_ok[faces[:, 1]] & vertex_ok[faces[:, 2]] & (area2.abs() > 1e-12)
    if cull_backfaces:
        # Counter-clockwise seen from the camera is clockwise in y-down image coordinates.
        keep &= area2 < 0
    cmin = torch.ceil(torch.minimum(torch.minimum(x0, x1), x2)).clamp(min=0)
    cmax = torch.floor(torch.maximum(torch.maximum(x0, x1), x2)).clamp(max=width - 1)
    rmin = torch.ceil(torch.minimum(torch.minimum(y0, y1), y2)).clamp(min=0)
    rmax = torch.floor(torch.maximum(torch.maximum(y0, y1), y2)).clamp(max=height - 1)
    keep &= (cmax >= cmin) & (rmax >= rmin)
    ids = torch.nonzero(keep).squeeze(1)
    if ids.numel() == 0:
        return _empty_fragments(height, width)

    # Barycentrics are affine in the sample position: l_i(p) = a_i px + b_i py + c_i; so is
    # the inverse depth sum_i l_i / z_i. Evaluate them relative to each bbox's corner sample
    # so that the per-pair float32 arithmetic only sees small offsets.
    area = _take(area2, ids)
    xs = (_take(x0, ids), _take(x1, ids), _take(x2, ids))
    ys = (_take(y0, ids), _take(y1, ids), _take(y2, ids))
    a = torch.stack([(ys[(i + 1) % 3] - ys[(i + 2) % 3]) / area for i in range(3)], dim=1)  # (Fk, 3)
    b = torch.stack([(xs[(i + 2) % 3] - xs[(i + 1) % 3]) / area for i in range(3)], dim=1)
    c = torch.stack(
        [(xs[(i + 1) % 3] * ys[(i + 2) % 3] - xs[(i + 2) % 3] * ys[(i + 1) % 3]) / area for i in range(3)],
        dim=1,
    )
    cmin, rmin, cmax, rmax = (_take(v, ids) for v in (cmin, rmin, cmax, rmax))
    corner = a * cmin[:, None] + b * rmin[:, None] + c
    inv_z = 1.0 / torch.stack([_take(z, _take(f, ids)) for f in corners], dim=1)
    box_w = (cmax - cmin + 1).to(torch.int64)
    box_h = (rmax - rmin + 1).to(torch.int64)
    cmin_i, rmin_i = cmin.to(torch.int64), rmin.to(torch.int64)

    # Sort triangles into buckets of power-of-two bbox sizes; every table below is in that order,
    # so a chunk of a bucket is a contiguous slice (no per-chunk gathers).
    bucket = _ceil_pow2_exponent(box_w) * 64 + _ceil_pow2_exponent(box_h)
    order = torch.argsort(bucket, stable=True)
    bucket = _take(bucket, order)
    table = _take(torch.cat([corner, a, b], dim=1), order).to(
        torch.float32
    )  # (Fk, 9): corner l0..2, a0..2, b0..2
    depth_table = _take(
        torch.stack([(corner * inv_z).sum(1), (a * inv_z).sum(1), (b * inv_z).sum(1)], dim=1), order
    ).to(torch.float32)  # (Fk, 3): inverse depth at the corner and its x, y slopes
    box_w_s, box_h_s = _take(box_w, order), _take(box_h, order)
    base_s = _take(rmin_i * width + cmin_i, order)  # flat index of the bbox corner sample
    local_ids = order  # position in the kept-triangle list

    codes, counts = torch.unique_consecutive(bucket, return_counts=True)
    sample_chunks: list[torch.Tensor] = []
    key_chunks: list[torch.Tensor] = []
    start = 0
    for code, count in zip(codes.tolist(), counts.tolist(), strict=True):
        bw, bh = 1 << (code // 64), 1 << (code % 64)
        ox = torch.arange(bw, dtype=torch.int64).repeat(bh)
        oy = torch.arange(bh, dtype=torch.int64).repeat_interleave(bw)
        oxf, oyf = ox.to(torch.float32), oy.to(torch.float32)
        offset = oy * width + ox
        per_chunk = max(1, max_pairs // (bw * bh))
        for lo in range(start, start + count, per_chunk):
            hi = min(lo + per_chunk, start + count)
            tab = table[lo:hi]
            valid = (ox < box_w_s[lo:hi, None]) & (oy < box_h_s[lo:hi, None])
            for i in range(3):
                lam = torch.addcmul(
                    torch.addcmul(tab[:, i : i + 1], tab[:, 3 + i : 4 + i], oxf), tab[:, 6 + i : 7 + i], oyf
                )
                valid &= lam >= -INSIDE_EPS
            g, p = torch.nonzero(valid, as_tuple=True)
            if g.numel() == 0:
                continue
            w_coef = _take(depth_table[lo:hi], g)
            w = torch.addcmul(
                torch.addcmul(w_coef[:, 0], w_coef[:, 1], _take(oxf, p)), w_coef[:, 2], _take(oyf, p)
            )
            depth_bits = (1.0 / w.clamp(min=1e-30)).view(torch.int32).to(torch.int64)
            key_chunks.append((depth_bits << _TRI_BITS) | _take(local_ids, lo + g))
            sample_chunks.append(_take(base_s, lo + g) + _take(offset, p))
        start += count
    if not sample_chunks:
        return _empty_fragments(height, width)

    keys = torch.full((height * width,), _EMPTY_KEY, dtype=torch.int64)
    keys.scatter_reduce_(0, torch.cat(sample_chunks), torch.cat(key_chunks), reduce="amin")
    samples = torch.nonzero(keys != _EMPTY_KEY).squeeze(1)
    local = keys[samples] & _TRI_MASK

    # --- resolve the visible triangle of each covered sample (float64) --------------------
    rows = _take(torch.cat([corner, a, b, inv_z, cmin[:, None], rmin[:, None]], dim=1), local)  # one gather
    ox = (samples % width).to(torch.float64) - rows[:, 12]
    oy = (samples // width).to(torch.float64) - rows[:, 13]
    lam = torch.addcmul(torch.addcmul(rows[:, 0:3], rows[:, 3:6], ox[:, None]), rows[:, 6:9], oy[:, None])
    q = lam.clamp(min=0.0) * rows[:, 9:12]
    q_sum = q[:, 0:1] + q[:, 1:2] + q[:, 2:3]
    return Fragments(
        samples=samples,
        triangle=_take(ids, local),
        bary=(q / q_sum).to(torch.float32),
        depth=(1.0 / q_sum.squeeze(1)).to(torch.float32),
        height=height,
        width=width,
    )


def _empty_fragments(height: int, width: int) -> Fragments:
    return Fragments(
        samples=torch.zeros(0, dtype=torch.int64),
        triangle=torch.zeros(0, dtype=torch.int64),
        bary=torch.zeros((0, 3), dtype=torch.float32),
        depth=torch.zeros(0, dtype=torch.float32),
        height=height,
        width=width,
    )


def _take(values: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``values[index]`` along dim 0 (index_select: several times faster than advanced indexing on CPU)."""
    return torch.index_select(values, 0, index)


def interpolate_face_table(fragments: Fragments, face_values: torch.Tensor) -> torch.Tensor:
    """Perspective-correct interpolation of per-face-corner values (F, 3, C) at covered samples -> (N, C)."""
    corners = _take(face_values.to(torch.float32).reshape(face_values.shape[0], -1), fragments.triangle)
    corners = corners.reshape(-1, 3, face_values.shape[2])
    bary = fragments.bary
    return bary[:, 0:1] * corners[:, 0] + bary[:, 1:2] * corners[:, 1] + bary[:, 2:3] * corners[:, 2]


def interpolate(fragments: Fragments, faces: torch.Tensor, attributes: torch.Tensor) -> torch.Tensor:
    """Perspective-correct interpolation of per-vertex ``attributes`` (V, C) at the covered samples -> (N, C).

    ``faces`` (F, 3) indexes ``attributes``; pass ``uv_faces`` with ``uv`` for texture coordinates.
    """
    face_values = _take(attributes.to(torch.float32), faces.to(torch.int64).reshape(-1))
    return interpolate_face_table(fragments, face_values.reshape(faces.shape[0], 3, -1))


def sample_texture(texture: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear, clamp-to-edge lookup of ``texture`` (Ht, Wt, C) float at ``uv`` (N, 2) -> (N, C).

    ``uv = (0, 0)`` is the bottom-left corner of the image, ``(1, 1)`` the top-right.
    """
    height, width, channels = texture.shape
    x = uv[:, 0].to(torch.float32) * width - 0.5
    y = (1.0 - uv[:, 1].to(torch.float32)) * height - 0.5
    x0 = torch.floor(x)
    y0 = torch.floor(y)
    fx = (x - x0)[:, None]
    fy = (y - y0)[:, None]
    x0i = x0.to(torch.int64)
    y0i = y0.to(torch.int64)
    x1i = (x0i + 1).clamp(0, width - 1)
    y1i = (y0i + 1).clamp(0, height - 1)
    x0i = x0i.clamp(0, width - 1)
    y0i = y0i.clamp(0, height - 1)
    flat = texture.reshape(-1, channels)
    top = torch.lerp(_take(flat, y0i * width + x0i), _take(flat, y0i * width + x1i), fx)
    bottom = torch.lerp(_take(flat, y1i * width + x0i), _take(flat, y1i * width + x1i), fx)
    return torch.lerp(top, bottom, fy)


def vertex_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted unit vertex normals (V, 3) of a mesh with counter-clockwise outward faces."""
    faces = faces.to(torch.int64)
    v = vertices.to(torch.float32)
    tri = v[faces]
    face_normal = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=1)
    normals = torch.zeros_like(v)
    for i in range(3):
        normals.index_add_(0, faces[:, i], face_normal)
    return normals / normals.norm(dim=1, keepdim=True).clamp(min=1e-12)


@dataclass
class TexturedMesh:
    """Connectivity and appearance of a textured triangle mesh (positions come per frame)."""

    faces: torch.Tensor  # (F, 3) int64 into the vertices
    uv: torch.Tensor  # (Vt, 2) float32 in [0, 1]
    uv_faces: torch.Tensor  # (F, 3) int64 into uv
    texture: torch.Tensor  # (Ht, Wt, 3) float32 in [0, 255]
    face_uv: torch.Tensor | None = None  # (F, 3, 2) uv of each face corner (filled in by __post_init__)

    def __post_init__(self) -> None:
        if self.face_uv is None:
            self.face_uv = self.uv[self.uv_faces]

    @classmethod
    def from_arrays(cls, faces, uv, uv_faces, texture) -> TexturedMesh:
        faces_t = torch.as_tensor(np.asarray(faces), dtype=torch.int64)
        uv_t = torch.as_tensor(np.asarray(uv), dtype=torch.float32)
        uv_faces_t = torch.as_tensor(np.asarray(uv_faces), dtype=torch.int64)
        tex = np.asarray(texture)
        if faces_t.ndim != 2 or faces_t.shape[1] != 3:
            raise ValueError(f"faces must be (F, 3), got {tuple(faces_t.shape)}")
        if uv_faces_t.shape != faces_t.shape:
            raise ValueError(
                f"uv_faces must match faces {tuple(faces_t.shape)}, got {tuple(uv_faces_t.shape)}"
            )
        if uv_t.ndim != 2 or uv_t.shape[1] != 2:
            raise ValueError(f"uv must be (Vt, 2), got {tuple(uv_t.shape)}")
        if int(uv_faces_t.max()) >= uv_t.shape[0] or int(uv_faces_t.min()) < 0:
            raise ValueError("uv_faces index outside uv")
        if tex.ndim != 3 or tex.shape[2] != 3:
            raise ValueError(f"texture must be (H, W, 3), got {tex.shape}")
        return cls(faces_t, uv_t, uv_faces_t, torch.as_tensor(tex, dtype=torch.float32).contiguous())


def render_mesh(
    mesh: TexturedMesh,
    vertices_world: torch.Tensor | np.ndarray,
    camera: Camera,
    *,
    supersample: int = 2,
    vertex_shade: torch.Tensor | np.ndarray | None = None,
    cull_backfaces: bool = False,
    near: float = DEFAULT_NEAR,
) -> RenderResult:
    """Render ``mesh`` posed at ``vertices_world`` (V, 3) through ``camera``.

    ``vertex_shade`` (V,) or (V, 3) (coloured light) optionally multiplies the texture colour
    (Gouraud, interpolated perspective-correctly); None renders the bare texture (unlit).
    """
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    verts = torch.as_tensor(
        np.asarray(vertices_world) if not torch.is_tensor(vertices_world) else vertices_world
    )
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise ValueError(f"vertices must be (V, 3), got {tuple(verts.shape)}")
    if int(mesh.faces.max()) >= verts.shape[0]:
        raise ValueError(
            f"faces index vertex {int(mesh.faces.max())} but only {verts.shape[0]} vertices given"
        )
    s = int(supersample)
    K = supersampled_intrinsics(camera.K, s)
    xy, z = project_points(verts, K, torch.as_tensor(camera.R), torch.as_tensor(camera.t))
    frags = rasterize(
        xy, z, mesh.faces, camera.height * s, camera.width * s, cull_backfaces=cull_backfaces, near=near
    )

    uv = interpolate_face_table(frags, mesh.face_uv)
    rgb = sample_texture(mesh.texture, uv)
    if vertex_shade is not None:
        shade = torch.as_tensor(
            np.asarray(vertex_shade) if not torch.is_tensor(vertex_shade) else vertex_shade
        )
        rgb = rgb * interpolate(frags, mesh.faces, shade.reshape(shade.shape[0], -1))

    # Box filter the samples into pixels: accumulate colour, count and depth per output pixel.
    num_pixels = camera.height * camera.width
    pixel = (frags.samples // frags.width // s) * camera.width + (frags.samples % frags.width) // s
    sums = torch.zeros((num_pixels, 5), dtype=torch.float32)
    sums.index_add_(
        0, pixel, torch.cat([rgb, torch.ones_like(frags.depth)[:, None], frags.depth[:, None]], dim=1)
    )
    count = sums[:, 3]
    coverage = count / float(s * s)
    mask = coverage >= 0.5
    image = sums[:, :3] * (mask.to(torch.float32) / float(s * s))[:, None]
    mean_depth = torch.where(count > 0, sums[:, 4] / count.clamp(min=1.0), torch.zeros(1))
    shape = (camera.height, camera.width)
    return RenderResult(
        image=image.round().clamp(0, 255).to(torch.uint8).reshape(shape + (3,)).numpy(),
        mask=(mask.to(torch.uint8) * 255).reshape(shape).numpy(),
        coverage=coverage.reshape(shape).numpy(),
        depth=mean_depth.reshape(shape).numpy(),
    )
