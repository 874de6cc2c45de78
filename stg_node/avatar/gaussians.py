"""The Gaussian table: every per-Gaussian parameter of the avatar in one place, and its initialisation.

As in SpacetimeGaussians, a Gaussian's static attributes (canonical centre, log-scales,
rotation, opacity logit, colour) and its temporal ones (motion polynomial, rotation polynomial,
temporal centre and scale) sit side by side as rows of named tensors, each with its own
learning rate. Row operations (append, keep) act on every column at once, so densification
never leaves a column behind; the optimiser state follows through :mod:`stg_node.avatar.optim`.

Columns (N rows each; all float32):

==================  ===============  =========================================================
name                shape            meaning
==================  ===============  =========================================================
means               (N, 3)           centre in the canonical big-pose space (metres, model axes)
log_scales          (N, 3)           log standard deviations along the rotated axes
quats               (N, 4)           rotation in canonical space, wxyz (c_0 of the rotation polynomial)
opacity_logits      (N,)             logit of the base opacity sigma_i
sh                  (N, K, 3)        SH colour coefficients (colour mode "sh"; K = (degree + 1)^2)
features            (N, F)           appearance feature fed to the colour MLP (colour mode "mlp")
skin_weights        (N, 24)          skinning weights from the body (fixed; rows sum to 1)
skin_delta          (N, 24)          learned log-space correction of skin_weights (optional)
motion_gate         (N,)             1 where the Gaussian may move (its motion terms learn), else 0
motion              (N, n_p, 3)      b_ik: centre offset polynomial, canonical frame (optional)
rot_motion          (N, n_q, 4)      c_ik, k >= 1: rotation polynomial (optional)
t_center            (N,)             mu_i^tau: temporal centre, normalised time units
t_log_scale         (N,)             log s_i: temporal scale, normalised time units
==================  ===============  =========================================================
"""

from __future__ import annotations

import math

import torch
from torch import nn

from stg_node.avatar.config import ModelConfig

# Columns the optimiser never updates (carried along by row operations only).
FIXED_COLUMNS = frozenset({"skin_weights", "motion_gate"})


def logit(p: float) -> float:
    return math.log(p / (1.0 - p))


class GaussianTable(nn.Module):
    """Named per-Gaussian tensors with a common first dimension N."""

    def __init__(self, columns: dict[str, torch.Tensor]):
        super().__init__()
        counts = {name: t.shape[0] for name, t in columns.items()}
        if len(set(counts.values())) > 1:
            raise ValueError(f"every column needs the same number of rows, got {counts}")
        self.params = nn.ParameterDict()
        for name, tensor in columns.items():
            self.params[name] = nn.Parameter(tensor.detach().clone(), requires_grad=name not in FIXED_COLUMNS)
        #: Bumped by every edit of the rows (append, prune, a column set anew): what caches built
        #: on the rows (the rigidity neighbour graph) compare, never ``id()`` of a tensor, which
        #: a new tensor may reuse once the old one is freed.
        self.version = 0

    def rows_changed(self) -> None:
        """Say that rows were added, removed or replaced (done by set_column and the optimiser)."""
        self.version += 1

    @property
    def num(self) -> int:
        return int(next(iter(self.params.values())).shape[0])

    def __contains__(self, name: str) -> bool:
        return name in self.params

    def __getitem__(self, name: str) -> torch.Tensor:
        return self.params[name]

    def get(self, name: str) -> torch.Tensor | None:
        return self.params[name] if name in self.params else None

    def names(self) -> list[str]:
        return list(self.params.keys())

    def trainable_names(self) -> list[str]:
        return [n for n in self.params if n not in FIXED_COLUMNS]

    def set_column(self, name: str, tensor: torch.Tensor) -> None:
        self.params[name] = nn.Parameter(tensor.detach().clone(), requires_grad=name not in FIXED_COLUMNS)
        self.rows_changed()

    # --- activated views ----------------------------------------------------------------------
    def scales(self) -> torch.Tensor:
        return self.params["log_scales"].exp()

    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.params["opacity_logits"])

    def motion_gate(self) -> torch.Tensor | None:
        """(N,) bool: Gaussians allowed to move (None when the model has no motion terms)."""
        gate = self.params.get("motion_gate") if "motion_gate" in self.params else None
        return None if gate is None else gate.detach() > 0.5

    def motion_active(self) -> torch.Tensor:
        """(N,) bool: rows with any non-zero motion or rotation-motion coefficient."""
        active = torch.zeros(self.num, dtype=torch.bool, device=self.params["means"].device)
        for name in ("motion", "rot_motion"):
            if name in self.params:
                active |= (self.params[name].detach() != 0).flatten(1).any(dim=1)
        return active

    def nbytes(self) -> int:
        return sum(p.numel() * p.element_size() for p in self.params.values())


def cap_scale_ratio(scales: torch.Tensor, max_ratio: float) -> torch.Tensor:
    """``scales`` (N, 3) with every axis raised to at least ``largest / max_ratio`` (0: unchanged).

    A Gaussian far longer than it is thick is a needle: under a pose it was never trained in it
    sticks out of the body as a streak. The cap keeps the posed largest / smallest axis ratio at
    most ``max_ratio``; the gradient of a raised axis goes to the largest one (torch.maximum).
    """
    if max_ratio <= 0:
        return scales
    floor = scales.max(dim=1, keepdim=True).values / max_ratio
    return torch.maximum(scales, floor)


def scale_ratio_percentile(scales: torch.Tensor, q: float = 99.0) -> float:
    """The ``q``-th percentile over Gaussians of largest / smallest axis of ``scales`` (N, 3)."""
    if scales.shape[0] == 0:
        return float("nan")
    ratio = scales.max(dim=1).values / scales.min(dim=1).values.clamp_min(1e-12)
    return float(torch.quantile(ratio.detach().double().cpu(), q / 100.0))


def sample_surface(
    vertices: torch.Tensor, faces: torch.Tensor, count: int, generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Area-weighted samples on a triangle mesh: (points (n, 3), face index (n,), barycentrics (n, 3))."""
    tri = vertices[faces]  # (F, 3, 3)
    area = 0.5 * torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).norm(dim=1)
    face = torch.multinomial(area / area.sum(), count, replacement=True, generator=generator)
    r1 = torch.rand(count, generator=generator, dtype=vertices.dtype).sqrt()
    r2 = torch.rand(count, generator=generator, dtype=vertices.dtype)
    bary = torch.stack([1 - r1, r1 * (1 - r2), r1 * r2], dim=1)
    points = (tri[face] * bary[..., None]).sum(dim=1)
    return points, face, bary


def surface_skin_weights(
    faces: torch.Tensor, vertex_weights: torch.Tensor, face: torch.Tensor, bary: torch.Tensor, mode: str
) -> torch.Tensor:
    """Skinning weights of surface samples: the barycentric blend of their triangle's vertex weights,
    or those of the nearest corner."""
    corner = vertex_weights[faces[face]]  # (n, 3, 24)
    if mode == "nearest":
        return corner[torch.arange(face.shape[0]), bary.argmax(dim=1)]
    weights = (corner * bary[..., None]).sum(dim=1)
    return weights / weights.sum(dim=1, keepdim=True).clamp_min(1e-12)


def mean_spacing(area: float, count: int) -> float:
    """Typical distance between ``count`` uniform samples on a surface of ``area`` m^2."""
    return math.sqrt(area / max(count, 1))


def new_columns(
    config: ModelConfig,
    means: torch.Tensor,
    skin_weights: torch.Tensor,
    scale: torch.Tensor | float,
    *,
    opacity: float = 0.5,
    t_center: torch.Tensor | float = 0.0,
    t_scale: torch.Tensor | float | None = None,
    rgb: torch.Tensor | None = None,
    generator: torch.Generator | None = None,
    dynamic: bool = False,
    normals: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """Fresh rows for every column the config asks for (used at init, by re-sampling and by tests).

    With surface ``normals`` (n, 3) each Gaussian is a disc in the surface: its local z axis along
    the normal, that axis ``config.init_flatness`` times the others; without, a sphere.
    """
    n = means.shape[0]
    dtype, device = means.dtype, means.device
    scale_t = torch.as_tensor(scale, dtype=dtype, device=device).expand(n).clamp_min(1e-6)
    log_scales = scale_t.log()[:, None].expand(n, 3).clone()
    quats = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=dtype, device=device).expand(n, 4).clone()
    if normals is not None and config.init_flatness != 1.0:
        quats = quaternion_z_to(normals.to(dtype))
        log_scales[:, 2] += math.log(config.init_flatness)
    cols: dict[str, torch.Tensor] = {
        "means": means,
        "log_scales": log_scales,
        "quats": quats,
        "opacity_logits": torch.full((n,), logit(opacity), dtype=dtype, device=device),
        "skin_weights": skin_weights,
    }
    if config.color == "sh":
        k = (config.sh_degree + 1) ** 2
        sh = torch.zeros(n, k, 3, dtype=dtype, device=device)
        if rgb is not None:
            sh[:, 0] = (rgb - 0.5) / 0.28209479177387814
        cols["sh"] = sh
    else:
        feats = torch.zeros(n, config.feature_dim, dtype=dtype, device=device)
        if generator is not None:
            feats.copy_(torch.randn(feats.shape, generator=generator, dtype=dtype) * 0.1)
        cols["features"] = feats
    if config.learn_skin_weights:
        cols["skin_delta"] = torch.zeros(n, skin_weights.shape[1], dtype=dtype, device=device)
    if config.n_p > 0 or config.n_q > 0:
        cols["motion_gate"] = torch.full((n,), float(dynamic), dtype=dtype, device=device)
    if config.n_p > 0:
        cols["motion"] = torch.zeros(n, config.n_p, 3, dtype=dtype, device=device)
    if config.n_q > 0:
        cols["rot_motion"] = torch.zeros(n, config.n_q, 4, dtype=dtype, device=device)
    if config.spacetime:
        scale_time = config.init_time_scale if t_scale is None else t_scale
        cols["t_center"] = torch.as_tensor(t_center, dtype=dtype, device=device).expand(n).clone()
        cols["t_log_scale"] = (
            torch.as_tensor(scale_time, dtype=dtype, device=device).expand(n).clamp_min(1e-6).log().clone()
        )
    return cols


def init_table(
    config: ModelConfig,
    vertices: torch.Tensor,
    faces: torch.Tensor,
    vertex_weights: torch.Tensor,
    generator: torch.Generator,
    *,
    t_center: float = 0.0,
) -> GaussianTable:
    """``config.num_gaussians`` Gaussians on the canonical body surface (``vertices``: the big-pose mesh)."""
    points, face, bary = sample_surface(vertices, faces, config.num_gaussians, generator)
    weights = surface_skin_weights(faces, vertex_weights, face, bary, config.skin_init)
    tri = vertices[faces]
    cross = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = float(0.5 * cross.norm(dim=1).sum())
    scale = config.init_scale_factor * mean_spacing(area, config.num_gaussians)
    normals = cross[face] / cross[face].norm(dim=1, keepdim=True).clamp_min(1e-12)
    cols = new_columns(
        config, points, weights, scale, opacity=0.5, t_center=t_center, generator=generator, normals=normals
    )
    return GaussianTable(cols)


def quaternion_z_to(directions: torch.Tensor) -> torch.Tensor:
    """(n, 4) unit wxyz quaternions turning the z axis onto unit ``directions`` (n, 3) (shortest arc)."""
    x, y, z = directions.unbind(-1)
    q = torch.stack([1.0 + z, -y, x, torch.zeros_like(z)], dim=-1)
    flipped = torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=directions.dtype, device=directions.device)
    q = torch.where((1.0 + z)[:, None] < 1e-9, flipped.expand_as(q), q)  # z onto -z: half turn about x
    return q / q.norm(dim=1, keepdim=True)
