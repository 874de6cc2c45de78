#!/usr/bin/env python
"""Render a body model in a few poses to a small PNG (docs/open_body.png by default).

An independent, deliberately simple mesh renderer (painter's algorithm with OpenCV polygon
fills, flat Lambert shading, the albedo sampled at each face's UV centre): no Gaussian splatting,
nothing shared with the avatar code, so the picture shows what the body model itself produces.

    python tools/render_body.py                      # the open body
    python tools/render_body.py --model /path/to/smpl --out /tmp/smpl.png
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stg_node.body import BIG_POSE, load_body_model  # noqa: E402
from stg_node.logs import configure_logging  # noqa: E402
from stg_node.threads import configure_threads  # noqa: E402


def demo_poses() -> dict[str, np.ndarray]:
    """Named (24, 3) axis-angle poses that exercise the main joints (SMPL axes: x left, y up, z front)."""
    d = np.deg2rad
    poses = {"rest (T-pose)": np.zeros((24, 3)), "big pose": np.asarray(BIG_POSE, dtype=np.float64)}
    walk = np.zeros((24, 3))
    walk[1, 0], walk[4, 0] = d(-35), d(20)  # left hip forward, knee slightly bent
    walk[2, 0], walk[5, 0] = d(25), d(45)  # right hip back, knee bent
    walk[16, 2], walk[17, 2] = d(-70), d(70)  # arms down
    walk[16, 1], walk[17, 1] = d(-25), d(25)
    walk[18, 1], walk[19, 1] = d(-40), d(40)  # elbows bent forward
    walk[3, 1], walk[12, 1] = d(8), d(-8)
    poses["walking"] = walk
    wave = np.zeros((24, 3))
    wave[16, 2] = d(60)  # left arm raised
    wave[18, 2] = d(70)  # elbow bent up
    wave[17, 2] = d(75)  # right arm down
    wave[19, 1] = d(80)  # right elbow forward 80 degrees
    wave[15, 1] = d(25)  # head turned
    wave[0, 1] = d(20)  # whole body turned a little
    poses["waving"] = wave
    squat = np.zeros((24, 3))
    squat[1, 0], squat[2, 0] = d(-90), d(-90)
    squat[4, 0], squat[5, 0] = d(100), d(100)
    squat[7, 0], squat[8, 0] = d(-15), d(-15)
    squat[3, 0], squat[6, 0] = d(20), d(10)
    squat[16, 1], squat[17, 1] = d(-70), d(70)
    squat[16, 2], squat[17, 2] = d(-20), d(20)
    poses["squat"] = squat
    return poses


def face_albedo(model) -> np.ndarray:
    """(F, 3) colour per face: the texture at the face's UV centre, or a neutral grey."""
    faces = model.faces.cpu().numpy()
    if model.texture is None or model.uv is None:
        return np.full((len(faces), 3), 180.0)
    texture = model.texture
    h, w = texture.shape[:2]
    centre = model.uv.cpu().numpy()[model.uv_faces.cpu().numpy()].mean(1)
    px = np.clip((centre[:, 0] * w).astype(int), 0, w - 1)
    py = np.clip(((1 - centre[:, 1]) * h).astype(int), 0, h - 1)
    return texture[py, px].astype(np.float64)


def render_mesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    albedo: np.ndarray,
    size=(240, 360),
    yaw_deg: float = 20.0,
    scale: float | None = None,
    background=(255, 255, 255),
) -> np.ndarray:
    """Orthographic view from the front (+z), turned by ``yaw_deg`` about y; returns H x W x 3 uint8 RGB.

    ``scale`` is pixels per metre (default: fit the mesh)."""
    import cv2

    width, height = size
    yaw = np.deg2rad(yaw_deg)
    rot = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
    v = vertices @ rot.T
    centre = 0.5 * (v.min(0) + v.max(0))
    if scale is None:
        scale = 0.9 * min(width / np.ptp(v[:, 0]).clip(1e-6), height / np.ptp(v[:, 1]).clip(1e-6))
    px = np.stack([(v[:, 0] - centre[0]) * scale + width / 2, -(v[:, 1] - centre[1]) * scale + height / 2], 1)
    tri = v[faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True).clip(1e-12)
    light = np.array([0.3, 0.5, 1.0]) / np.linalg.norm([0.3, 0.5, 1.0])
    shade = 0.35 + 0.65 * np.abs(normals @ light)
    colours = np.clip(albedo * shade[:, None], 0, 255).astype(np.uint8)
    order = np.argsort(tri[:, :, 2].mean(1))  # far (small z) first: the camera looks down -z
    image = np.full((height, width, 3), background, dtype=np.uint8)
    pts = np.round(px[faces] * 16).astype(np.int32)
    for f in order:
        cv2.fillConvexPoly(image, pts[f], colours[f].tolist(), lineType=cv2.LINE_AA, shift=4)
    return image


def render_poses(model, poses: dict[str, np.ndarray], panel=(240, 360)) -> np.ndarray:
    import cv2
    import torch

    faces = model.faces.cpu().numpy()
    albedo = face_albedo(model)
    batch = torch.as_tensor(np.stack([p.reshape(72) for p in poses.values()]), dtype=model.v_template.dtype)
    vertices = model(poses=batch).vertices.detach().cpu().numpy()
    # One scale for every panel (the widest pose fits), so poses compare at the same size.
    extent = max(max(np.ptp(v[:, 0]) / panel[0], np.ptp(v[:, 1]) / panel[1]) for v in vertices)
    scale = 0.92 / extent
    panels = []
    for name, verts in zip(poses, vertices, strict=True):
        image = render_mesh(verts, faces, albedo, size=panel, scale=scale)
        cv2.putText(image, name, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (40, 40, 40), 1, cv2.LINE_AA)
        panels.append(image)
    return np.concatenate(panels, axis=1)


def main(argv=None) -> int:
    import cv2

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default=None, help="SMPL file or folder (default: the open body)")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "open_body.png")
    args = parser.parse_args(argv)
    configure_logging()
    configure_threads()
    model = load_body_model(args.model)
    image = render_poses(model, demo_poses())
    args.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.out), cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(f"wrote {args.out} ({args.out.stat().st_size / 1e3:.0f} kB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
