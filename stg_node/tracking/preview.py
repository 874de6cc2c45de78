"""A look at the fit before training: the input with the fitted SMPL mesh and the person mask drawn over it.

``stg-track INPUT --out POSES.npz --preview fit.mp4`` and ``stg-train --format video`` (into the
run folder, before it trains) write one preview frame per input frame, at the input's frame
rate, the long side at most ``max_side`` pixels:

- the person mask as a green tint with its outline;
- the SMPL mesh of the fit, shaded by how it faces the camera, blended over the image (drawn
  with the benchmark's z-buffered mesh rasterizer, so limbs occlude each other correctly);
- a bar and a line of text at the top: frame number, confidence, the flags that lowered it, and
  ``SKIPPED`` in red when the confidence is below the training threshold.

A wrong field of view, a flipped body, a mask that took in a chair or a pose frozen in the
prior's rest pose are visible here in seconds, before minutes of training are spent on them.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import torch

from stg_node.progress import progress as progress_bar

log = logging.getLogger(__name__)

MESH_RGB = np.array([90.0, 150.0, 255.0])  # the fitted body, a light blue
MASK_RGB = np.array([40.0, 220.0, 80.0])  # the person mask, green
MESH_ALPHA = 0.55
MASK_ALPHA = 0.3
BAR_PX = 22
SKIP_RGB = (230, 40, 40)
KEEP_RGB = (40, 200, 80)


def mesh_overlay(
    vertices_camera: np.ndarray, faces: np.ndarray, K: np.ndarray, width: int, height: int
) -> tuple[np.ndarray, np.ndarray]:
    """(shade (H, W) float32 in [0, 1], coverage (H, W) bool) of a mesh given in camera coordinates."""
    from stg_node.data.synth.mesh_raster import interpolate, project_points, rasterize, vertex_normals

    verts = torch.as_tensor(np.asarray(vertices_camera, np.float64))
    faces_t = torch.as_tensor(np.asarray(faces), dtype=torch.int64)
    xy, z = project_points(verts, torch.as_tensor(K), torch.eye(3, dtype=torch.float64), torch.zeros(3))
    frags = rasterize(xy, z, faces_t, height, width)
    shade = np.zeros(height * width, np.float32)
    covered = np.zeros(height * width, bool)
    if frags.samples.numel():
        normals = vertex_normals(verts.to(torch.float32), faces_t)
        n = interpolate(frags, faces_t, normals)
        n = n / n.norm(dim=1, keepdim=True).clamp_min(1e-9)
        points = interpolate(frags, faces_t, verts.to(torch.float32))
        view = -points / points.norm(dim=1, keepdim=True).clamp_min(1e-9)
        facing = (n * view).sum(dim=1).abs()
        samples = frags.samples.numpy()
        shade[samples] = (0.35 + 0.65 * facing).numpy()
        covered[samples] = True
    return shade.reshape(height, width), covered.reshape(height, width)


def draw_frame(
    image_rgb: np.ndarray,
    mask: np.ndarray | None,
    shade: np.ndarray,
    covered: np.ndarray,
    text: str,
    confidence: float,
    skipped: bool,
) -> np.ndarray:
    """One preview frame (RGB uint8): mask tint and outline, shaded mesh, the status bar."""
    out = np.asarray(image_rgb, np.float64).copy()
    if mask is not None and mask.any():
        m = mask > 0
        out[m] = (1 - MASK_ALPHA) * out[m] + MASK_ALPHA * MASK_RGB
    if covered.any():
        body = MESH_RGB[None] * shade[covered][:, None]
        out[covered] = (1 - MESH_ALPHA) * out[covered] + MESH_ALPHA * body
    out = np.clip(out, 0, 255).astype(np.uint8)
    if mask is not None and mask.any():
        contours, _ = cv2.findContours(
            (mask > 0).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE
        )
        cv2.drawContours(out, contours, -1, tuple(int(c) for c in MASK_RGB), 1, cv2.LINE_AA)
    width = out.shape[1]
    out[:BAR_PX] = (out[:BAR_PX] * 0.3).astype(np.uint8)
    cv2.rectangle(out, (0, BAR_PX - 4), (int(round(confidence * (width - 1))), BAR_PX - 1),
                  SKIP_RGB if skipped else KEEP_RGB, -1)  # fmt: skip
    cv2.putText(out, text, (4, BAR_PX - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.42,
                SKIP_RGB if skipped else (255, 255, 255), 1, cv2.LINE_AA)  # fmt: skip
    if skipped:
        cv2.rectangle(out, (0, 0), (width - 1, out.shape[0] - 1), SKIP_RGB, 2)
    return out


def write_preview(
    source: str | Path,
    poses_path: str | Path,
    out: str | Path,
    *,
    masks_dir: str | Path | None = None,
    smpl_model: str | None = None,
    fps: float | None = None,
    min_confidence: float = 0.5,
    max_side: int = 640,
    progress: bool = True,
) -> int:
    """Write the preview of ``source`` tracked into ``poses_path`` to ``out`` (.mp4); returns its frames.

    ``masks_dir``: the tracker's masks (``{frame:06d}.png``), drawn when there; ``min_confidence``:
    frames below it are marked SKIPPED (what the trainer will leave out)."""
    from stg_node.body import load_body_model
    from stg_node.tracking.poses_file import read_poses
    from stg_node.tracking.sources import open_source

    out = Path(out)
    if out.suffix.lower() != ".mp4":
        raise ValueError(f"the preview must be an .mp4 file, got {out}")
    tracked = read_poses(poses_path)
    body = load_body_model(smpl_model)
    faces = body.faces.cpu().numpy()
    rows = {int(f): i for i, f in enumerate(tracked.frames)}
    flags = tracked.flags if tracked.flags is not None else np.array([""] * len(tracked))
    frames = open_source(source, fps if fps is not None else (tracked.fps or None))
    width, height = frames.width, frames.height
    scale = min(1.0, max_side / max(width, height))
    size = (max(2, round(width * scale) // 2 * 2), max(2, round(height * scale) // 2 * 2))  # even: codecs
    sx, sy = size[0] / width, size[1] / height
    K = np.array(tracked.K, np.float64)
    K[0] *= sx
    K[0, 2] = (tracked.K[0, 2] + 0.5) * sx - 0.5
    K[1] *= sy
    K[1, 2] = (tracked.K[1, 2] + 0.5) * sy - 0.5
    out.parent.mkdir(parents=True, exist_ok=True)
    writer = cv2.VideoWriter(str(out), cv2.VideoWriter_fourcc(*"mp4v"), float(frames.fps or 30.0), size)
    if not writer.isOpened():
        raise OSError(f"cannot open {out} for writing an MP4 (OpenCV VideoWriter)")
    written = 0
    bar = progress_bar(total=len(frames) or None, unit="frame", desc="fit preview", enabled=progress)
    try:
        for frame in frames:
            image = cv2.resize(frame.image, size, interpolation=cv2.INTER_AREA)
            row = rows.get(frame.index)
            mask = None
            if masks_dir is not None:
                mask_file = Path(masks_dir) / f"{frame.index:06d}.png"
                if mask_file.is_file():
                    mask = cv2.resize(cv2.imread(str(mask_file), cv2.IMREAD_GRAYSCALE), size,
                                      interpolation=cv2.INTER_NEAREST)  # fmt: skip
            shade, covered = np.zeros(size[::-1], np.float32), np.zeros(size[::-1], bool)
            if row is None:
                confidence, text, skipped = 0.0, f"frame {frame.index}: not tracked", True
            else:
                confidence = float(tracked.confidence[row])
                skipped = confidence < min_confidence
                if confidence > 0:
                    vertices = _vertices(body, tracked, row)
                    shade, covered = mesh_overlay(vertices, faces, K, size[0], size[1])
                why = str(flags[row]).replace(",", ", ")
                text = f"frame {frame.index}  confidence {confidence:.2f}" + (f"  {why}" if why else "")
                if skipped:
                    text = "SKIPPED  " + text
            writer.write(cv2.cvtColor(draw_frame(image, mask, shade, covered, text, confidence, skipped),
                                      cv2.COLOR_RGB2BGR))  # fmt: skip
            written += 1
            bar.update(1)
    finally:
        bar.close()
        writer.release()
    log.info("fit preview of %d frames -> %s", written, out)
    return written


def _vertices(body, tracked, row: int) -> np.ndarray:
    with torch.no_grad():
        output = body(
            betas=torch.as_tensor(tracked.shapes[row : row + 1], dtype=torch.float32),
            poses=torch.as_tensor(tracked.poses[row : row + 1], dtype=torch.float32),
            Rh=torch.as_tensor(tracked.Rh[row : row + 1], dtype=torch.float32),
            Th=torch.as_tensor(tracked.Th[row : row + 1], dtype=torch.float32),
        )
    return output.vertices[0].double().numpy()
