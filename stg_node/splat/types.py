"""The data that crosses the line between `rasterize()` (api.py) and a backend.

Every backend (backend.py names the interface) receives a `RenderRequest` and answers a
`BackendOutput`: image and alpha without background, the accumulated depth when asked, the
per-Gaussian `Projection` and `RenderStats`. The api layer owns everything shared: argument
checks, the empty-scene guard, quaternion sanitising, backend choice, background, expected
depth and the `info` dict. Nothing here knows a particular backend.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch


class BackendUnavailable(RuntimeError):
    """A backend cannot run on this machine (missing compiler, gsplat, CUDA toolkit ...).

    `rasterize(backend="auto")` falls back to the torch reference on it (warning once); a
    backend named explicitly lets it propagate."""


@dataclass
class Projection:
    """Screen-space Gaussians, one row per input Gaussian (culled rows are zero)."""

    means2d: torch.Tensor  # [N, 2] pixels; differentiable; .grad / .absgrad after backward
    conics: torch.Tensor  # [N, 3] inverse 2D covariance (a, b, c); differentiable
    depths: torch.Tensor  # [N] camera z; differentiable
    opacities: torch.Tensor  # [N] effective opacity (x compensation); differentiable
    radii: torch.Tensor  # [N, 2] int32 screen radius in pixels (x, y); 0 = culled
    bbox: torch.Tensor | None  # [N, 4] int32 inclusive pixel box x0, x1, y0, y1; None (cuda)
    visible: torch.Tensor  # [N] bool: radii > 0 (docs/SPLAT.md, "Which Gaussians are visible")

    def drawn(self) -> torch.Tensor:
        """[N] bool: visible and covering at least one pixel centre (a non-empty pixel box).

        A visible Gaussian's box can be empty: gsplat's rule keeps one whose extent reaches
        less than half a pixel into the image, and so do we, but no pixel centre sees it."""
        if self.bbox is None:
            return self.visible
        b = self.bbox
        return self.visible & (b[:, 0] <= b[:, 1]) & (b[:, 2] <= b[:, 3])


@dataclass(frozen=True)
class RenderOptions:
    """The per-call settings of `rasterize()` that backends act on (validated by the api)."""

    near_plane: float
    far_plane: float
    eps2d: float
    radius_clip: float
    antialiased: bool
    render_depth: bool  # also return the accumulated depth sum(w z) as BackendOutput.depth
    max_intersections: int  # cpu backend: tile intersections per chunk


@dataclass
class RenderRequest:
    """One camera's render: Gaussians (validated, quaternions sanitised) and options."""

    means: torch.Tensor  # [N, 3]
    quats: torch.Tensor  # [N, 4] wxyz, none with every |component| < QUAT_NORM_EPS
    scales: torch.Tensor  # [N, 3] activated
    opacities: torch.Tensor  # [N] activated
    colors: torch.Tensor  # [N, C]
    viewmat: torch.Tensor  # [4, 4] world-to-camera
    K: torch.Tensor  # [3, 3]
    width: int  # >= 1 (the api answers zero-area images itself)
    height: int  # >= 1
    options: RenderOptions


@dataclass
class RenderStats:
    """What a backend reports about one render."""

    n_intersections: int = -1  # tile-Gaussian pairs it processed (-1: not known)
    # Per-stage timings and counters, backend-specific; a backend may add its backward
    # stages here when backward runs (the cpu backend does: "backward", "project_backward").
    stages: dict[str, dict[str, float]] = field(default_factory=dict)


@dataclass
class BackendOutput:
    """A backend's answer; all tensors in the dtype of the request's Gaussians."""

    image: torch.Tensor  # [H, W, C] without background
    alpha: torch.Tensor  # [H, W, 1]
    depth: torch.Tensor | None  # [H, W, 1] accumulated sum(w z) when options.render_depth
    projection: Projection
    stats: RenderStats


class AbsGradHolder:
    """Lets a backend's backward add AbsGS statistics to ``tensor.absgrad`` (accumulating)."""

    def __init__(self, tensor: torch.Tensor):
        self.tensor = tensor

    def add_absgrad(self, index: torch.Tensor | None, values: torch.Tensor) -> None:
        t = self.tensor
        current = getattr(t, "absgrad", None)
        if current is None:
            current = torch.zeros(t.shape, dtype=t.dtype, device=t.device)
        values = values.to(dtype=t.dtype, device=t.device)
        if index is None:
            current = current + values
        else:
            current = current.index_add(0, index, values)
        t.absgrad = current
