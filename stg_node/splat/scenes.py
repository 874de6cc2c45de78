"""Synthetic Gaussian scenes and cameras for tests, benchmarks and docs images.

`person_sized_scene` fills the surfaces of a rough standing figure (head, torso, pelvis,
arms, legs as spheres/capsules, 1.8 m tall, Y-up, feet on y=0, facing +z) with Gaussians the
size a trained avatar has (3 mm to 3 cm, flattened along the surface normal), opacities in
[0.3, 1] and per-part colours. It is only geometry: the renderer's benchmarks need a
realistic depth complexity and screen footprint, not a body model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

# (kind, parameters): spheres (centre, radius) and capsules (end a, end b, radius), metres.
_PARTS = [
    ("sphere", (0.0, 1.66, 0.0), 0.11, (0.85, 0.67, 0.55)),  # head
    ("capsule", (0.0, 1.06, 0.0), (0.0, 1.42, 0.0), 0.16, (0.2, 0.35, 0.7)),  # torso
    ("capsule", (-0.09, 0.92, 0.0), (0.09, 0.92, 0.0), 0.12, (0.25, 0.25, 0.3)),  # pelvis
    ("capsule", (-0.21, 1.45, 0.0), (-0.27, 1.16, 0.02), 0.05, (0.2, 0.35, 0.7)),  # upper arms
    ("capsule", (0.21, 1.45, 0.0), (0.27, 1.16, 0.02), 0.05, (0.2, 0.35, 0.7)),
    ("capsule", (-0.27, 1.16, 0.02), (-0.29, 0.88, 0.08), 0.04, (0.85, 0.67, 0.55)),  # forearms
    ("capsule", (0.27, 1.16, 0.02), (0.29, 0.88, 0.08), 0.04, (0.85, 0.67, 0.55)),
    ("capsule", (-0.1, 0.88, 0.0), (-0.11, 0.48, 0.01), 0.075, (0.25, 0.25, 0.3)),  # thighs
    ("capsule", (0.1, 0.88, 0.0), (0.11, 0.48, 0.01), 0.075, (0.25, 0.25, 0.3)),
    ("capsule", (-0.11, 0.48, 0.01), (-0.11, 0.07, -0.01), 0.055, (0.25, 0.25, 0.3)),  # shins
    ("capsule", (0.11, 0.48, 0.01), (0.11, 0.07, -0.01), 0.055, (0.25, 0.25, 0.3)),
    ("capsule", (-0.11, 0.04, 0.0), (-0.11, 0.04, 0.16), 0.04, (0.1, 0.1, 0.1)),  # feet
    ("capsule", (0.11, 0.04, 0.0), (0.11, 0.04, 0.16), 0.04, (0.1, 0.1, 0.1)),
]


def _part_area(part) -> float:
    if part[0] == "sphere":
        return 4 * math.pi * part[2] ** 2
    a, b, r = torch.tensor(part[1]), torch.tensor(part[2]), part[3]
    return 2 * math.pi * r * float((b - a).norm()) + 4 * math.pi * r * r


def _sample_part(part, n: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """n points on the part's surface and their outward normals."""
    d = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    d = d / d.norm(dim=1, keepdim=True).clamp_min(1e-12)
    if part[0] == "sphere":
        centre, radius = torch.tensor(part[1], dtype=torch.float64), part[2]
        return centre + radius * d, d
    a = torch.tensor(part[1], dtype=torch.float64)
    b = torch.tensor(part[2], dtype=torch.float64)
    r = part[3]
    axis = b - a
    u = torch.rand(n, 1, generator=gen, dtype=torch.float64)
    base = a + u * axis
    unit = axis / axis.norm()
    radial = d - (d @ unit)[:, None] * unit  # normal of the cylinder part
    radial = radial / radial.norm(dim=1, keepdim=True).clamp_min(1e-12)
    return base + r * radial, radial


def _quat_from_normal(normals: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """Quaternions (wxyz) rotating local z onto the normal, with a random twist about it."""
    z = torch.tensor([0.0, 0.0, 1.0], dtype=normals.dtype)
    axis = torch.linalg.cross(z.expand_as(normals), normals)
    sin = axis.norm(dim=1)
    cos = normals[:, 2]
    angle = torch.atan2(sin, cos)
    axis = axis / sin.clamp_min(1e-12)[:, None]
    align = torch.cat([torch.cos(angle / 2)[:, None], axis * torch.sin(angle / 2)[:, None]], dim=1)
    twist_angle = torch.rand(normals.shape[0], generator=gen, dtype=normals.dtype) * 2 * math.pi
    twist = torch.stack(
        [
            torch.cos(twist_angle / 2),
            torch.zeros_like(twist_angle),
            torch.zeros_like(twist_angle),
            torch.sin(twist_angle / 2),
        ],
        dim=1,
    )
    w1, x1, y1, z1 = align.unbind(1)
    w2, x2, y2, z2 = twist.unbind(1)
    return torch.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        dim=1,
    )


@dataclass
class Scene:
    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor

    def params(self) -> tuple[torch.Tensor, ...]:
        return self.means, self.quats, self.scales, self.opacities, self.colors

    def to(self, device=None, dtype=None) -> Scene:
        return Scene(*(t.to(device=device, dtype=dtype) for t in self.params()))


def person_sized_scene(n: int, seed: int = 0, min_scale: float = 0.003, max_scale: float = 0.03) -> Scene:
    """n Gaussians on a 1.8 m standing figure (see the module docstring); float32, CPU."""
    gen = torch.Generator().manual_seed(seed)
    areas = torch.tensor([_part_area(p) for p in _PARTS])
    counts = torch.floor(areas / areas.sum() * n).long()
    counts[0] += n - int(counts.sum())
    means, normals, colors = [], [], []
    for part, count in zip(_PARTS, counts.tolist(), strict=True):
        if count == 0:
            continue
        p, nrm = _sample_part(part, count, gen)
        jitter = torch.randn(count, 3, generator=gen, dtype=torch.float64) * 0.004
        means.append(p + jitter)
        normals.append(nrm)
        base = torch.tensor(part[-1], dtype=torch.float64)
        colors.append((base + 0.08 * torch.randn(count, 3, generator=gen, dtype=torch.float64)).clamp(0, 1))
    means_t, normals_t, colors_t = torch.cat(means), torch.cat(normals), torch.cat(colors)
    log_s = torch.empty(n, 2, dtype=torch.float64)
    log_s.uniform_(math.log(min_scale), math.log(max_scale), generator=gen)
    tangential = log_s.exp()
    scales = torch.cat([tangential, tangential.min(dim=1, keepdim=True).values * 0.3], dim=1)
    quats = _quat_from_normal(normals_t, gen)
    opacities = torch.empty(n, dtype=torch.float64).uniform_(0.3, 1.0, generator=gen)
    return Scene(
        means=means_t.float(),
        quats=quats.float(),
        scales=scales.float(),
        opacities=opacities.float(),
        colors=colors_t.float(),
    )


def front_camera(
    width: int, height: int, distance: float = 3.0, fill: float = 0.85, subject_height: float = 1.8
) -> tuple[torch.Tensor, torch.Tensor]:
    """(viewmat, K) of a camera `distance` m in front of the figure, framing it to `fill`."""
    f = fill * height * distance / subject_height
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    centre_y = subject_height / 2
    # OpenCV axes: camera x = world +x, camera y = world -y (down), camera z = world -z.
    viewmat = torch.tensor(
        [[1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, centre_y], [0.0, 0.0, -1.0, distance], [0.0, 0.0, 0.0, 1.0]]
    )
    return viewmat, K


def random_camera(width: int, height: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """A random rigid world-to-camera matrix and a pinhole K with an off-centre principal point."""
    gen = torch.Generator().manual_seed(seed + 7919)
    q = torch.randn(4, generator=gen, dtype=torch.float64)
    w, x, y, z = (q / q.norm()).tolist()
    R = torch.tensor(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ],
        dtype=torch.float64,
    )
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3] = R
    viewmat[:3, 3] = torch.randn(3, generator=gen, dtype=torch.float64)
    f = 0.9 * max(width, height)
    cx = width / 2 + 0.13 * width * float(torch.rand(1, generator=gen) - 0.5)
    cy = height / 2 + 0.13 * height * float(torch.rand(1, generator=gen) - 0.5)
    K = torch.tensor([[f, 0.0, cx], [0.0, 1.05 * f, cy], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return viewmat.float(), K.float()


def random_scene(
    n: int, width: int, height: int, seed: int = 0, channels: int = 3, max_opacity: float = 0.95
) -> tuple[Scene, torch.Tensor, torch.Tensor]:
    """n overlapping Gaussians of mixed sizes in (and slightly around) a random camera's view.

    Returns (scene, viewmat, K); float32 on the CPU. Used to compare backends.
    """
    viewmat, K = random_camera(width, height, seed)
    gen = torch.Generator().manual_seed(seed)
    f, cx, cy = float(K[0, 0]), float(K[0, 2]), float(K[1, 2])
    depth = torch.empty(n, dtype=torch.float64).uniform_(1.5, 6.0, generator=gen)
    # Pixel positions spread 15 % beyond the image, so some Gaussians straddle the border.
    u = torch.empty(n, dtype=torch.float64).uniform_(-0.15 * width, 1.15 * width, generator=gen)
    v = torch.empty(n, dtype=torch.float64).uniform_(-0.15 * height, 1.15 * height, generator=gen)
    cam = torch.stack([(u - cx) / f * depth, (v - cy) / (1.05 * f) * depth, depth], dim=1)
    R, t = viewmat[:3, :3].double(), viewmat[:3, 3].double()
    world = (cam - t) @ R  # R^T (cam - t)
    log_s = torch.empty(n, 3, dtype=torch.float64).uniform_(math.log(0.005), math.log(0.3), generator=gen)
    scene = Scene(
        means=world.float(),
        quats=torch.randn(n, 4, generator=gen).float(),
        scales=log_s.exp().float(),
        opacities=torch.empty(n).uniform_(0.05, max_opacity, generator=gen),
        colors=torch.rand(n, channels, generator=gen),
    )
    return scene, viewmat, K
