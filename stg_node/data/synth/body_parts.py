"""Which body part every pixel of a synthetic view shows: head, torso, arms, hands, legs, feet.

The benchmark writes the true surface of every frame (``new_vertices/``), so a view's pixels can
be labelled exactly: the surface is rasterized into the camera with the benchmark's own
z-buffered rasterizer (one sample at each pixel centre, the z-buffer decides what is seen), and
each visible triangle carries the part of its vertices (the part of a vertex is the group of its
strongest skinning joint; a triangle across a border takes the part two of its corners share).
Scores per part (:class:`PartErrors`) then say where an avatar loses quality: a pose error shows
on the hands and arms long before the torso.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from stg_node.data.synth.mesh_raster import project_points, rasterize
from stg_node.data.types import Camera

# SMPL joint indices per part.
PARTS: dict[str, tuple[int, ...]] = {
    "head": (12, 15),
    "torso": (0, 3, 6, 9, 13, 14),
    "arms": (16, 17, 18, 19),
    "hands": (20, 21, 22, 23),
    "legs": (1, 2, 4, 5),
    "feet": (7, 8, 10, 11),
}
PART_NAMES = tuple(PARTS)
BACKGROUND = -1


def vertex_parts(skin_weights: np.ndarray) -> np.ndarray:
    """(V,) int8 part index (into PART_NAMES) of each vertex, from its strongest joint."""
    weights = np.asarray(skin_weights)
    if weights.ndim != 2 or weights.shape[1] != 24:
        raise ValueError(f"skinning weights must be (V, 24), got {weights.shape}")
    lookup = np.full(24, BACKGROUND, np.int8)
    for index, joints in enumerate(PARTS.values()):
        lookup[list(joints)] = index
    return lookup[np.argmax(weights, axis=1)]


def face_parts(faces: np.ndarray, parts_of_vertices: np.ndarray) -> np.ndarray:
    """(F,) int8: the part two (or three) corners of each triangle share, else its first corner's."""
    p = np.asarray(parts_of_vertices)[np.asarray(faces)]
    return np.where((p[:, 1] == p[:, 2]) & (p[:, 0] != p[:, 1]), p[:, 1], p[:, 0]).astype(np.int8)


def part_labels(
    vertices: np.ndarray, faces: np.ndarray, parts_of_faces: np.ndarray, camera: Camera
) -> np.ndarray:
    """(H, W) int8: the part seen at each pixel centre of ``camera``, BACKGROUND (-1) off the body."""
    points = torch.as_tensor(np.asarray(vertices, np.float64))
    faces_t = torch.as_tensor(np.asarray(faces), dtype=torch.int64)
    height, width = int(camera.height), int(camera.width)
    xy, z = project_points(
        points, np.asarray(camera.K), np.asarray(camera.R), np.asarray(camera.t).reshape(3)
    )
    frags = rasterize(xy, z, faces_t, height, width)
    labels = np.full(height * width, BACKGROUND, np.int8)
    if frags.samples.numel():
        labels[frags.samples.numpy()] = np.asarray(parts_of_faces)[frags.triangle.numpy()]
    return labels.reshape(height, width)


class PartErrors:
    """Squared errors summed per part over many views; PSNR per part from the pooled error.

    Pooling (rather than averaging each view's PSNR) keeps a part that fills three pixels of one
    view from swinging the figure."""

    def __init__(self):
        self.sum_sq = np.zeros(len(PART_NAMES))
        self.count = np.zeros(len(PART_NAMES), np.int64)

    def add(self, pred: np.ndarray, target: np.ndarray, labels: np.ndarray) -> None:
        """``pred`` and ``target`` (H, W, 3) uint8; ``labels`` (H, W) from :func:`part_labels`."""
        if pred.shape != target.shape or pred.shape[:2] != labels.shape:
            raise ValueError(
                f"shapes differ: pred {pred.shape}, target {target.shape}, labels {labels.shape}"
            )
        err = ((pred.astype(np.float64) - target.astype(np.float64)) / 255.0) ** 2
        per_pixel = err.mean(axis=-1)
        for index in range(len(PART_NAMES)):
            on = labels == index
            self.sum_sq[index] += per_pixel[on].sum()
            self.count[index] += int(on.sum())

    def psnr(self) -> dict[str, float]:
        """Part name -> PSNR (dB) over its pixels; NaN for a part never seen."""
        out = {}
        for index, name in enumerate(PART_NAMES):
            if self.count[index] == 0:
                out[name] = math.nan
                continue
            mse = self.sum_sq[index] / self.count[index]
            out[name] = math.inf if mse == 0 else -10.0 * math.log10(mse)
        return out

    def pixels(self) -> dict[str, int]:
        return {name: int(self.count[i]) for i, name in enumerate(PART_NAMES)}
