#!/usr/bin/env python3
"""Make docs/synth_montage.png: a few frames and views of an stg-synth benchmark, and its garment motion.

Row 1: the training camera (Camera_B1) at one frame of each motion segment of the default
``mixed`` motion (the last one a held-out pose). Row 2: held-out cameras at one frame.
Row 3: the garment displacement |ground-truth vertex - skinned vertex| of row 1's frames,
seen from the training camera (black = skinning explains it, bright = up to the largest offset).

    python tools/synth_montage.py [--from DIR] [--out docs/synth_montage.png] [--tile 160]

Without ``--from`` it first generates a 300-frame benchmark at 384 x 384 into a temporary folder.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np


def _label(tile: np.ndarray, text: str) -> np.ndarray:
    tile = tile.copy()
    cv2.putText(tile, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.36, (255, 255, 255), 1, cv2.LINE_AA)
    return tile


def _tile(image_bgr: np.ndarray, size: int) -> np.ndarray:
    return cv2.resize(image_bgr, (size, size), interpolation=cv2.INTER_AREA)


def _garment_heat(folder: Path, frame: int, body, annots: dict, size: int, scale: float) -> np.ndarray:
    import torch

    from stg_node.data.synth.mesh_raster import TexturedMesh, render_mesh
    from stg_node.data.types import Camera
    from stg_node.safe_load import load_npy

    params = load_npy(folder / "new_params" / f"{frame}.npy")
    gt = np.load(folder / "new_vertices" / f"{frame}.npy")
    with torch.no_grad():
        skinned = (
            body(
                betas=torch.as_tensor(params["shapes"]),
                poses=torch.as_tensor(params["poses"]),
                Rh=torch.as_tensor(params["Rh"]),
                Th=torch.as_tensor(params["Th"]),
            )
            .vertices[0]
            .numpy()
        )
    offset = np.linalg.norm(gt - skinned, axis=1)
    white = np.full((2, 2, 3), 255, np.uint8)
    faces = body.faces.numpy()
    mesh = TexturedMesh.from_arrays(faces, np.zeros((1, 2)), np.zeros_like(faces), white)
    cams = annots["cams"]
    width = cv2.imread(str(folder / annots["ims"][0]["ims"][0])).shape[1]
    camera = Camera(K=cams["K"][0], R=cams["R"][0], t=cams["T"][0][:, 0] / 1000.0, width=width, height=width)
    shade = np.clip(offset / scale, 0.0, 1.0) * 0.95 + 0.05
    result = render_mesh(mesh, gt, camera, vertex_shade=shade, cull_backfaces=True)
    heat = cv2.applyColorMap(result.image[..., 0], cv2.COLORMAP_INFERNO)
    heat[result.mask == 0] = 0
    return _tile(heat, size)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--from", dest="source", type=Path, default=None, help="an existing stg-synth folder")
    parser.add_argument("--out", type=Path, default=Path("docs/synth_montage.png"))
    parser.add_argument("--tile", type=int, default=160)
    args = parser.parse_args(argv)

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from stg_node.body import load_body_model
    from stg_node.data.synth.generate import SynthConfig, generate
    from stg_node.data.synth.writer import read_metadata
    from stg_node.logs import configure_logging
    from stg_node.safe_load import load_npy
    from stg_node.threads import configure_threads

    configure_logging("WARNING")
    configure_threads()
    body = load_body_model()
    with tempfile.TemporaryDirectory(prefix="synth_montage_") as tmp:
        folder = args.source
        if folder is None:
            folder = Path(tmp) / "bench"
            generate(SynthConfig(out=folder, seed=0, size=384), body=body)
        meta = read_metadata(folder)
        annots = load_npy(folder / "annots.npy")
        segments = meta["motion_segments"]
        frames = [(seg["start"] + seg["stop"]) // 2 for seg in segments]
        n_train = meta["num_train_frames"]
        names = [seg["name"] + (" (novel)" if seg["start"] >= n_train else "") for seg in segments]
        row1 = [
            _label(_tile(cv2.imread(str(folder / annots["ims"][f]["ims"][0])), args.tile), f"B1 f{f} {name}")
            for f, name in zip(frames, names, strict=True)
        ]
        view_frame = max(f for f in meta["rendered"]["Camera_B2"] if f < n_train)
        row2 = []
        for cam in meta["cameras"][1 : len(row1) + 1]:
            image = cv2.imread(str(folder / annots["ims"][view_frame]["ims"][cam["index"]]))
            row2.append(
                _label(_tile(image, args.tile), f"{cam['name'].replace('Camera_', '')} f{view_frame}")
            )
        scale = meta["garment"]["max_offset_m"]
        row3 = [
            _label(_garment_heat(folder, f, body, annots, args.tile, scale), f"garment f{f}") for f in frames
        ]
        width = len(row1)
        blank = np.zeros_like(row1[0])
        rows = [r + [blank] * (width - len(r)) for r in (row1, row2, row3)]
        montage = np.concatenate([np.concatenate(r, axis=1) for r in rows], axis=0)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(args.out), montage, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(f"wrote {args.out} ({montage.shape[1]}x{montage.shape[0]})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
