#!/usr/bin/env python3
"""Make docs/self_shadow.png: what ``stg-synth --self-shadow`` adds, on a few frames of a subject.

Per frame (columns), from the training camera: the subject lit by its room light without
self-shadowing, with it (what ``--self-shadow`` writes), and the ambient occlusion alone (white =
the whole sky open, black = none of it).

    python tools/self_shadow_figure.py --from DIR [--frames 100 112 124 136 148] [--out docs/self_shadow.png]

``DIR``: a subject generated with ``--shading room`` (the tradeoff condition ``room_self_shadow``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--from", dest="folder", required=True)
    p.add_argument("--frames", type=int, nargs="+", default=[100, 112, 124, 136, 148])
    p.add_argument("--out", default=str(REPO / "docs" / "self_shadow.png"))
    p.add_argument("--tile", type=int, default=200)
    args = p.parse_args(argv)

    import torch

    from stg_node.body import load_body_model
    from stg_node.data.synth.generate import _outward_faces
    from stg_node.data.synth.lighting import lighting
    from stg_node.data.synth.mesh_raster import TexturedMesh, render_mesh, vertex_normals
    from stg_node.data.synth.occlusion import ambient_occlusion
    from stg_node.data.synth.writer import read_metadata
    from stg_node.data.types import Camera
    from stg_node.safe_load import load_npy

    folder = Path(args.folder)
    meta = read_metadata(folder)
    body = load_body_model()
    annots = np.load(folder / "annots.npy", allow_pickle=True).item()
    cams = annots["cams"]
    size = int(meta["size"][0])
    camera = Camera(
        name="Camera_B1",
        K=np.asarray(cams["K"][0], np.float64),
        R=np.asarray(cams["R"][0], np.float64),
        t=np.asarray(cams["T"][0], np.float64).reshape(3) / 1000.0,
        width=size,
        height=size,
    )
    rest = np.load(folder / "new_vertices" / "0.npy")  # winding is a property of the faces only
    faces, flipped = _outward_faces(rest - rest.mean(0), np.asarray(body.faces))
    uv_faces = np.asarray(body.uv_faces)[:, [0, 2, 1]] if flipped else np.asarray(body.uv_faces)
    textured = TexturedMesh.from_arrays(faces, np.asarray(body.uv), uv_faces, body.texture)
    white = TexturedMesh.from_arrays(
        faces, np.zeros((1, 2)), np.zeros_like(faces), np.full((2, 2, 3), 255, np.uint8)
    )
    light = lighting(meta["shading"]["mode"])
    rows = [[], [], []]
    for frame in args.frames:
        verts = torch.from_numpy(np.load(folder / "new_vertices" / f"{frame}.npy"))
        Rh = load_npy(folder / "new_params" / f"{frame}.npy")["Rh"].reshape(3)
        tri = torch.as_tensor(faces)
        for row, shade in enumerate(
            (
                light.vertex_shade(verts, tri, Rh),
                light.vertex_shade(verts, tri, Rh, self_shadow=True),
                ambient_occlusion(verts, vertex_normals(verts, tri), verts, tri),
            )
        ):
            mesh = white if row == 2 else textured
            image = render_mesh(
                mesh, verts, camera, supersample=2, vertex_shade=shade, cull_backfaces=True
            ).image
            tile = cv2.resize(image[:, :, ::-1], (args.tile, args.tile), interpolation=cv2.INTER_AREA)
            label = ("no self-shadow", "--self-shadow", "ambient occlusion")[row] + f"  frame {frame}"
            cv2.putText(tile, label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.36, (255, 255, 255), 1, cv2.LINE_AA)
            rows[row].append(tile)
    cv2.imwrite(args.out, np.concatenate([np.concatenate(r, axis=1) for r in rows], axis=0))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
