"""Where the garment is, from the synthetic benchmark's ground truth: its pixels in any view, and
which of an avatar's Gaussians sit on it.

The benchmark's cloth (:mod:`garment`) is a per-vertex looseness on the body mesh (the hem from
the chest down, the sleeves): a vertex with looseness > 0 moves with the cloth's dynamics, one
with 0 is skin or attached cloth that only skinning moves. A *garment face* is a face with a
loose vertex (it deforms). Both are recomputed from what ``synth.json`` records (the body's
shape and the garment's parameters), so any generated benchmark has them, old ones included.

- :func:`garment_pixels`: the pixels of a view where a garment face is what the camera sees:
  the true surface of that frame (``new_vertices/``) rasterized with the benchmark's own
  z-buffered rasterizer (:mod:`mesh_raster`, one sample at each pixel centre), as the
  fast-moving pixels are (:mod:`true_flow`). The trade-off study pools squared errors over
  these pixels into a "garment PSNR".
- :func:`on_garment`: for points in the avatar's canonical (big-pose) space, whether the
  nearest body vertex is loose: which Gaussians (those with active motion terms, say) lie on
  the garment.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch

from stg_node.data.synth.garment import GarmentParams, garment_regions
from stg_node.data.synth.mesh_raster import project_points, rasterize
from stg_node.data.synth.writer import read_frame_vertices, read_metadata
from stg_node.data.types import Camera


def garment_faces(faces, looseness) -> np.ndarray:
    """(F,) bool: faces with at least one loose vertex (``looseness`` (V,) > 0)."""
    faces = np.asarray(faces, dtype=np.int64)
    loose = np.asarray(looseness) > 0
    if faces.ndim != 2 or faces.shape[1] != 3 or (faces.size and faces.max() >= loose.shape[0]):
        raise ValueError(f"faces must be (F, 3) indices into {loose.shape[0]} vertices, got {faces.shape}")
    return loose[faces].any(axis=1)


def garment_pixels(vertices, faces, face_is_garment, camera: Camera) -> np.ndarray:
    """(H, W) bool: pixel centres of ``camera`` whose visible surface is a garment face.

    ``vertices`` (V, 3) world positions, ``faces`` (F, 3), ``face_is_garment`` (F,) bool; the
    z-buffer alone decides what is seen (no back-face culling, as :func:`true_flow.true_flow`).
    """
    verts = torch.as_tensor(np.asarray(vertices, np.float64))
    faces_t = torch.as_tensor(np.asarray(faces), dtype=torch.int64)
    is_garment = torch.as_tensor(np.asarray(face_is_garment, bool))
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise ValueError(f"vertices must be (V, 3), got {tuple(verts.shape)}")
    if is_garment.shape != (faces_t.shape[0],):
        raise ValueError(f"face_is_garment must be ({faces_t.shape[0]},), got {tuple(is_garment.shape)}")
    K = torch.as_tensor(np.asarray(camera.K, np.float64))
    R = torch.as_tensor(np.asarray(camera.R, np.float64))
    t = torch.as_tensor(np.asarray(camera.t, np.float64).reshape(3))
    height, width = int(camera.height), int(camera.width)
    xy, z = project_points(verts, K, R, t)
    frags = rasterize(xy, z, faces_t, height, width)
    out = np.zeros(height * width, bool)
    if frags.samples.numel():
        out[frags.samples.numpy()] = is_garment[frags.triangle].numpy()
    return out.reshape(height, width)


def rest_body(folder: str | Path, body=None) -> tuple[np.ndarray, np.ndarray]:
    """The generated subject's body at zero pose (as stg-synth built it): vertices (V, 3), joints (24, 3)."""
    if body is None:
        from stg_node.body import load_body_model

        body = load_body_model()
    betas = np.asarray(read_metadata(folder)["body"]["betas"], np.float32)
    zero = torch.zeros(1, 3)
    with torch.no_grad():
        rest = body(betas=torch.as_tensor(betas[None]), poses=torch.zeros(1, 72), Rh=zero, Th=zero)
    return rest.vertices[0].cpu().numpy(), rest.joints[0].cpu().numpy()


def benchmark_looseness(folder: str | Path, body=None) -> np.ndarray:
    """(V,) the cloth looseness of every body vertex of a generated benchmark (0 = not garment)."""
    meta = read_metadata(folder)
    known = {f.name for f in dataclasses.fields(GarmentParams)}
    params = GarmentParams(**{k: v for k, v in meta.get("garment", {}).items() if k in known})
    vertices, joints = rest_body(folder, body)
    return garment_regions(vertices, joints, params).weight


def benchmark_garment_pixels(
    folder: str | Path, frame: int, camera: Camera, faces, face_is_garment
) -> np.ndarray:
    """:func:`garment_pixels` of a generated benchmark's view of ``frame`` (its true surface)."""
    return garment_pixels(read_frame_vertices(folder, frame), faces, face_is_garment, camera)


def on_garment(points, canonical_vertices, looseness, chunk: int = 4096) -> np.ndarray:
    """(N,) bool: whether the body vertex nearest each canonical point (N, 3) is loose.

    ``canonical_vertices`` (V, 3): the same body, same shape, in the pose the points live in.
    """
    points = torch.as_tensor(np.asarray(points, np.float32))
    verts = torch.as_tensor(np.asarray(canonical_vertices, np.float32))
    loose = torch.as_tensor(np.asarray(looseness) > 0)
    if loose.shape != (verts.shape[0],):
        raise ValueError(f"looseness must be ({verts.shape[0]},), got {tuple(loose.shape)}")
    nearest = [
        torch.cdist(points[i : i + chunk], verts).argmin(dim=1) for i in range(0, points.shape[0], chunk)
    ]
    return loose[torch.cat(nearest)].numpy() if nearest else np.zeros(0, bool)
