"""Ground-truth image motion of the synthetic benchmark, and the "fast-moving" pixels it defines.

The benchmark writes the true surface of every frame (``new_vertices/``, garment included), so
the true optical flow of any view is known: no estimator (DIS, RAFT) and its errors are
involved. For a view of frame ``f`` through camera ``C``:

1. the surface at ``f`` is rasterized into ``C`` with the benchmark's own z-buffered mesh
   rasterizer (:mod:`mesh_raster`, one sample at each pixel centre, no back-face culling: the
   z-buffer alone decides what is seen);
2. the material point seen at each covered pixel has perspective-correct barycentric
   coordinates in its triangle; the same coordinates on the same triangle of the surface at the
   other frame give where that point went (exact for the mesh: a point keeps its barycentrics
   when the vertices move);
3. that 3D point is projected into ``C``; its pixel coordinates minus the pixel's own are the
   flow, in pixels per frame.

:func:`fast_region` thresholds the flow's magnitude: pixels whose true motion exceeds
``threshold_px`` pixels per frame (the trade-off study, tools/tradeoff.py, uses
:data:`FAST_FLOW_PX_AT_512` at 512 x 512, scaled with the image width). Everything runs in
float64 for the projection (as the rasterizer's setup) and returns float32.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from stg_node.data.synth.mesh_raster import interpolate, project_points, rasterize
from stg_node.data.synth.writer import read_frame_vertices
from stg_node.data.types import Camera

# The trade-off study's threshold: 5 px per frame at 512 x 512. The benchmark's cameras see the
# subject at about 150 px per metre (2.4 m of height framed in 360 px at 3.5 m), so at 30 fps
# that is a surface moving at about 1 m/s across the view: on the dance subject the swinging
# arms and hands, the hem and sleeves, the fastest twists (a quarter to a third of the body's
# pixels); on the still subject almost nothing (its breathing and head turns stay far below).
FAST_FLOW_PX_AT_512 = 5.0


@dataclass
class TrueFlow:
    """The true motion of what one camera sees at one frame."""

    flow: np.ndarray  # (H, W, 2) float32 pixels (x right, y down) to the other frame; 0 off the body
    covered: np.ndarray  # (H, W) bool: a pixel centre on the body

    @property
    def magnitude(self) -> np.ndarray:
        """(H, W) float32 |flow| in pixels, 0 off the body."""
        return np.linalg.norm(self.flow, axis=-1).astype(np.float32)


def true_flow(vertices: np.ndarray, other_vertices: np.ndarray, faces, camera: Camera) -> TrueFlow:
    """Motion of the surface visible at ``vertices`` (V, 3) to its place at ``other_vertices`` (V, 3).

    ``faces`` (F, 3) index both; ``camera`` is an OpenCV pinhole (world-to-camera ``R``, ``t`` in
    metres, ``K`` in pixels of its ``width`` x ``height`` image).
    """
    now = torch.as_tensor(np.asarray(vertices, np.float64))
    other = torch.as_tensor(np.asarray(other_vertices, np.float64))
    if now.ndim != 2 or now.shape[1] != 3 or now.shape != other.shape:
        raise ValueError(
            "vertices and other_vertices must both be (V, 3), got "
            f"{tuple(now.shape)} and {tuple(other.shape)}"
        )
    faces_t = torch.as_tensor(np.asarray(faces), dtype=torch.int64)
    if faces_t.numel() and int(faces_t.max()) >= now.shape[0]:
        raise ValueError(f"faces index vertex {int(faces_t.max())} but only {now.shape[0]} vertices given")
    K = torch.as_tensor(np.asarray(camera.K, np.float64))
    R = torch.as_tensor(np.asarray(camera.R, np.float64))
    t = torch.as_tensor(np.asarray(camera.t, np.float64).reshape(3))
    height, width = int(camera.height), int(camera.width)
    xy, z = project_points(now, K, R, t)
    frags = rasterize(xy, z, faces_t, height, width)
    flow = np.zeros((height * width, 2), np.float32)
    covered = np.zeros(height * width, bool)
    if frags.samples.numel():
        # interpolate() works in float32; carry the other frame's points relative to this frame's
        # so the float32 values are centimetres, not metres from the world origin.
        moved = interpolate(frags, faces_t, (other - now).to(torch.float32)).to(torch.float64)
        here = interpolate(frags, faces_t, now.to(torch.float32)).to(torch.float64)
        target_xy, _ = project_points(here + moved, K, R, t)
        source_xy, _ = project_points(here, K, R, t)
        samples = frags.samples.numpy()
        flow[samples] = (target_xy - source_xy).numpy().astype(np.float32)
        covered[samples] = True
    return TrueFlow(flow.reshape(height, width, 2), covered.reshape(height, width))


def fast_region(flow: TrueFlow, threshold_px: float) -> np.ndarray:
    """(H, W) bool: pixels on the body whose true motion exceeds ``threshold_px`` pixels per frame."""
    if not threshold_px >= 0:
        raise ValueError(f"threshold_px must be >= 0, got {threshold_px}")
    return flow.covered & (flow.magnitude > threshold_px)


def benchmark_true_flow(
    folder: str | Path, frame: int, camera: Camera, faces, num_frames: int, cuts=()
) -> TrueFlow:
    """True flow of a generated benchmark's view of ``frame``: to the next frame, or from the previous
    one for the last frame of the sequence (``num_frames``) or of a clip (the frame before one of
    ``cuts``, synth.json's ``held_out.cuts``), whose successor is not its continuation."""
    if not 0 <= frame < num_frames:
        raise ValueError(f"frame {frame} is outside the sequence 0..{num_frames - 1}")
    if num_frames < 2:
        raise ValueError("true flow needs a sequence of at least two frames")
    last_of_clip = frame + 1 >= num_frames or frame + 1 in set(cuts)
    other = frame - 1 if last_of_clip else frame + 1
    if other < 0:
        raise ValueError(f"frame {frame} is a clip of one frame: it has no true flow")
    return true_flow(read_frame_vertices(folder, frame), read_frame_vertices(folder, other), faces, camera)
