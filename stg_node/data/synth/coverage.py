"""How much of the body's surface the training cameras ever see, from the synthetic benchmark's truth.

A Gaussian on surface no training view shows has no detail to learn: its colour is whatever the
prior gives, so how many Gaussians a subject needs depends on how much of its surface is observed.
This module measures that on a generated benchmark: each training frame's true surface
(``new_vertices/``) is rasterized with the benchmark's own z-buffered rasterizer
(:mod:`mesh_raster`, no back-face culling, as :mod:`true_flow` and :mod:`garment_truth`) and a face
counts as *seen* in a view when it is the visible surface at one or more of its samples. Areas are
taken on the subject's rest body, so a face's weight does not change with the pose.

``supersample`` rasterizes at that many samples per pixel side: at 256 px a hand's or the face's
triangles are smaller than a pixel and would otherwise be missed by every sample although the
camera sees them.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from stg_node.data.synth.mesh_raster import project_points, rasterize, supersampled_intrinsics
from stg_node.data.synth.writer import read_frame_vertices
from stg_node.data.types import Camera


def seen_faces(vertices, faces, camera: Camera, supersample: int = 1) -> np.ndarray:
    """(F,) bool: faces of the surface ``vertices`` (V, 3) that are visible at some sample of ``camera``."""
    verts = torch.as_tensor(np.asarray(vertices, np.float64))
    faces_t = torch.as_tensor(np.asarray(faces), dtype=torch.int64)
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise ValueError(f"vertices must be (V, 3), got {tuple(verts.shape)}")
    if faces_t.ndim != 2 or faces_t.shape[1] != 3:
        raise ValueError(f"faces must be (F, 3), got {tuple(faces_t.shape)}")
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    K = supersampled_intrinsics(np.asarray(camera.K, np.float64), supersample).to(torch.float64)
    R = torch.as_tensor(np.asarray(camera.R, np.float64))
    t = torch.as_tensor(np.asarray(camera.t, np.float64).reshape(3))
    xy, z = project_points(verts, K, R, t)
    frags = rasterize(xy, z, faces_t, int(camera.height) * supersample, int(camera.width) * supersample)
    out = np.zeros(faces_t.shape[0], bool)
    if frags.triangle.numel():
        out[frags.triangle.unique().numpy()] = True
    return out


def face_areas(vertices, faces) -> np.ndarray:
    """(F,) triangle areas of the mesh ``vertices`` (V, 3), ``faces`` (F, 3)."""
    v = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64)]
    return 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)


@dataclass(frozen=True)
class Coverage:
    """Which faces the training views saw, and in how many of them."""

    views_seen: np.ndarray  # (F,) int: training views in which each face is visible
    area: np.ndarray  # (F,) rest-body face areas (m^2)
    views: int  # training views looked at

    def fraction_never_seen(self) -> float:
        """Share of the surface's area no training view shows."""
        return float(self.area[self.views_seen == 0].sum() / max(self.area.sum(), 1e-30))

    def fraction_seen_in_at_most(self, k: int) -> float:
        """Share of the area seen in at most ``k`` views."""
        return float(self.area[self.views_seen <= k].sum() / max(self.area.sum(), 1e-30))

    def fraction_seen_in_at_least(self, share: float) -> float:
        """Share of the area seen in at least ``share`` of the views (0..1)."""
        return float(self.area[self.views_seen >= share * self.views].sum() / max(self.area.sum(), 1e-30))


def coverage(
    views: Iterable[tuple[np.ndarray, Camera]], faces, rest_vertices, supersample: int = 1
) -> Coverage:
    """:class:`Coverage` of the surface over ``views``: (vertices (V, 3), camera) per training view."""
    area = face_areas(rest_vertices, faces)
    count = np.zeros(area.shape[0], np.int64)
    n = 0
    for vertices, camera in views:
        count += seen_faces(vertices, faces, camera, supersample)
        n += 1
    return Coverage(count, area, n)


def benchmark_coverage(
    folder: str | Path, samples: Iterable, faces, rest_vertices, supersample: int = 1
) -> Coverage:
    """:func:`coverage` of a generated benchmark over its training ``samples`` (each with ``.index``,
    the frame, and ``.camera``): the true surface of each sample's frame seen by its camera."""
    return coverage(
        ((read_frame_vertices(Path(folder), s.index), s.camera) for s in samples),
        faces,
        rest_vertices,
        supersample,
    )
