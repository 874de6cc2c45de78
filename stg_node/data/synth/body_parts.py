"""Scores per body part, from the synthetic benchmark's ground-truth surface.

Where an avatar fails under a new pose says why: hands and feet (small, fast, poorly skinned),
arms (bent far from any training pose), the torso (large, shaded differently when the body
turns). The benchmark knows its true surface at every frame (``new_vertices/``), so every pixel
of an evaluation view can be labelled with the body part seen there:

1. each vertex belongs to the part of the bone that moves it most (its largest skinning weight,
   :data:`JOINT_PART` maps SMPL's 24 joints to :data:`PARTS`); a triangle takes the part most of
   its corners have (the first corner's on a three-way tie);
2. the true surface of the view's frame is rasterized into the view's camera with the
   benchmark's z-buffered mesh rasterizer (one sample at each pixel centre, no back-face culling:
   the z-buffer alone decides what is seen);
3. a pixel's label is the part of the triangle seen there, -1 where the body is not.

:class:`RegionScores` pools squared errors per label over many views into one PSNR per part
(the pixels of a part, whatever view they come from, weigh alike), as the trade-off study's
fast-region PSNR does. Only pixels where the true body is count: an avatar that bleeds into the
background is caught by the whole-image scores, not by these.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from stg_node.data.synth.mesh_raster import project_points, rasterize
from stg_node.data.synth.writer import read_frame_vertices
from stg_node.data.types import Camera

PARTS = ("head", "torso", "arms", "hands", "legs", "feet")
JOINT_PART = {
    "pelvis": "torso",
    "spine1": "torso",
    "spine2": "torso",
    "spine3": "torso",
    "left_collar": "torso",
    "right_collar": "torso",
    "neck": "head",
    "head": "head",
    "left_shoulder": "arms",
    "right_shoulder": "arms",
    "left_elbow": "arms",
    "right_elbow": "arms",
    "left_wrist": "hands",
    "right_wrist": "hands",
    "left_hand": "hands",
    "right_hand": "hands",
    "left_hip": "legs",
    "right_hip": "legs",
    "left_knee": "legs",
    "right_knee": "legs",
    "left_ankle": "feet",
    "right_ankle": "feet",
    "left_foot": "feet",
    "right_foot": "feet",
}


def joint_parts(joint_names) -> np.ndarray:
    """(24,) index into :data:`PARTS` of each joint (SMPL order)."""
    missing = [name for name in joint_names if name not in JOINT_PART]
    if missing:
        raise ValueError(f"no body part for joints {missing}")
    return np.asarray([PARTS.index(JOINT_PART[name]) for name in joint_names], np.int64)


def face_parts(faces: np.ndarray, skin_weights: np.ndarray, joint_names) -> np.ndarray:
    """(F,) part index of each triangle: the part most of its corners belong to (see module doc)."""
    vertex_part = joint_parts(joint_names)[np.asarray(skin_weights).argmax(axis=1)]
    corners = vertex_part[np.asarray(faces, np.int64)]  # (F, 3)
    first, second, third = corners[:, 0], corners[:, 1], corners[:, 2]
    return np.where((second == third) & (second != first), second, first)


def part_labels(vertices: np.ndarray, faces: np.ndarray, face_part: np.ndarray, camera: Camera) -> np.ndarray:
    """(H, W) int64 part index seen at each pixel centre of ``camera``, -1 off the body."""
    verts = torch.as_tensor(np.asarray(vertices, np.float64))
    faces_t = torch.as_tensor(np.asarray(faces), dtype=torch.int64)
    K = torch.as_tensor(np.asarray(camera.K, np.float64))
    R = torch.as_tensor(np.asarray(camera.R, np.float64))
    t = torch.as_tensor(np.asarray(camera.t, np.float64).reshape(3))
    xy, z = project_points(verts, K, R, t)
    height, width = int(camera.height), int(camera.width)
    frags = rasterize(xy, z, faces_t, height, width)
    labels = np.full(height * width, -1, np.int64)
    labels[frags.samples.numpy()] = np.asarray(face_part)[frags.triangle.numpy()]
    return labels.reshape(height, width)


class SynthPartLabeller:
    """Part labels of any view of a generated benchmark: ``labeller(frame, camera) -> (H, W)``."""

    def __init__(self, folder: str | Path, body=None):
        from stg_node.body import SMPL_JOINT_NAMES, load_body_model

        body = body or load_body_model()
        self.folder = Path(folder)
        self.faces = body.faces.cpu().numpy()
        self.face_part = face_parts(self.faces, body.weights.cpu().numpy(), SMPL_JOINT_NAMES)

    def __call__(self, frame: int, camera: Camera) -> np.ndarray:
        return part_labels(read_frame_vertices(self.folder, frame), self.faces, self.face_part, camera)

    def regions(self, frame: int, camera: Camera) -> dict[str, np.ndarray]:
        """Part name -> (H, W) bool pixels of that part in this view."""
        labels = self(frame, camera)
        return {name: labels == i for i, name in enumerate(PARTS)}


class RegionScores:
    """Squared errors pooled per named region over many views -> one PSNR per region."""

    def __init__(self):
        self.sq_error: dict[str, float] = {}
        self.values: dict[str, int] = {}  # squared errors summed (pixels x channels)
        self.pixels: dict[str, int] = {}

    def add(self, pred: np.ndarray, target: np.ndarray, regions: dict[str, np.ndarray]) -> None:
        """``pred``, ``target``: (H, W, C) uint8 (or floats in [0, 1]); ``regions``: name -> (H, W) bool."""
        scale = 255.0 if np.asarray(pred).dtype == np.uint8 else 1.0
        diff = (np.asarray(pred, np.float64) - np.asarray(target, np.float64)) / scale
        for name, mask in regions.items():
            mask = np.asarray(mask, bool)
            sel = diff[mask]
            self.sq_error[name] = self.sq_error.get(name, 0.0) + float((sel**2).sum())
            self.values[name] = self.values.get(name, 0) + int(sel.size)
            self.pixels[name] = self.pixels.get(name, 0) + int(mask.sum())

    def psnr(self, name: str) -> float:
        """PSNR (dB, peak 1) over every pixel of region ``name`` added so far; NaN when it was never seen."""
        count = self.values.get(name, 0)
        if count == 0:
            return math.nan
        mse = self.sq_error[name] / count
        return math.inf if mse == 0 else -10.0 * math.log10(mse)

    def report(self) -> dict[str, dict]:
        """Region -> {psnr, pixels}: the pooled PSNR and how many pixels (over all views) it is over."""
        return {name: {"psnr": self.psnr(name), "pixels": self.pixels[name]} for name in self.sq_error}
