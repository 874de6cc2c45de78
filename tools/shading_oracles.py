"""Which factor of the shaded colour carries the novel-pose gap: oracles from the synthetic truth.

An avatar with shading renders ``albedo x E(normal)``; the benchmark's subject is
``true albedo x true shade`` (stg_node.data.synth.lighting). A lit subject and the same subject
under flat light (``stg-synth --shading none``: identical motion, cameras and masks) give the true
shade per pixel as their ratio. Each oracle swaps one learned factor for the truth, per pixel
where both the avatar and the true body are (elsewhere the avatar's render is kept), and scores
novel views and novel poses as stg-eval does (whole image, masked ground truth):

- ``learned``: the avatar as it renders (stg-eval's score);
- ``true_light``: the learned albedo and normals under the subject's true light (``--light``
  given, normalised to a mean irradiance of 1 as the learned one is);
- ``true_normals``: every Gaussian's normal replaced by the true posed surface's at its nearest
  vertex, under the learned light (``true_normals_light``: and under the true light);
- ``true_shade``: the learned albedo times the true shade (true light on the true surface's
  normals): what is left is the albedo and the geometry;
- ``true_albedo``: the true albedo (scaled by the light's mean) times the learned shade (the
  avatar's render over its albedo render): what is left is the light and the normals;
- ``albedo_only``: the learned albedo against the true one (a score of the albedo alone).

A factor whose oracle closes the gap between the splits carries it. Per body part as stg-eval
(stg_node.data.synth.body_parts). Only for lights fixed in the world without a sky term.

Usage: python tools/shading_oracles.py RUN --lit DIR --flat DIR [--json OUT]
(e.g. ``--lit runs/tradeoff_mid/data/room_turn_held_out_125f_256px_v4e10_s0 --flat
runs/tradeoff_mid/data/flat_turn_held_out_125f_256px_v4e10_s0``: the trade-off tool's room and flat
subjects share motion, cameras and masks.)
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
from pathlib import Path

import numpy as np


def true_light(lit_root: Path):
    """The lit subject's light as a LightSpec normalised to a mean irradiance of 1, and that mean."""
    from stg_node.avatar.shading import LightSpec
    from stg_node.data.synth.writer import read_metadata

    shading = read_metadata(lit_root)["shading"]
    if shading.get("sky"):
        raise ValueError("a sky term is not a distant light: no oracle light for it")
    ambient = np.asarray(shading["ambient"], np.float64)
    directions = np.asarray([light["direction"] for light in shading["lights"]], np.float64).reshape(-1, 3)
    colors = np.asarray([light["color"] for light in shading["lights"]], np.float64).reshape(-1, 3)
    if any(light.get("frame", "world") != "world" for light in shading["lights"]):
        raise ValueError("a light turning with the body: no world light to swap in")
    mean = ambient + colors.sum(axis=0) / 4.0
    return LightSpec.distant(ambient / mean, directions, colors / mean), mean


@contextlib.contextmanager
def true_surface_normals(lit_root: Path, frame: int, faces):
    """Within: every Gaussian's normal is the true posed surface's at its nearest vertex."""
    import torch

    from stg_node.avatar import model as model_module
    from stg_node.data.synth.mesh_raster import vertex_normals
    from stg_node.data.synth.writer import read_frame_vertices

    vertices = torch.as_tensor(read_frame_vertices(lit_root, frame))
    normals = vertex_normals(vertices, torch.as_tensor(np.asarray(faces), dtype=torch.int64)).float()
    original = model_module.gaussian_normals

    def replaced(quats, scales, means, camera_center, outward=False):
        nearest = torch.cat([torch.cdist(m, vertices).argmin(dim=1) for m in means.detach().split(4096)])
        return normals[nearest]

    model_module.gaussian_normals = replaced
    try:
        yield
    finally:
        model_module.gaussian_normals = original


def score(run: Path, lit_root: Path, flat_root: Path, splits=("novel_view", "novel_pose")) -> dict:
    from stg_node.avatar.data_spec import DataSpec
    from stg_node.avatar.loading import corrected, load_run_renderer
    from stg_node.avatar.shading import LightSpec
    from stg_node.data.synth.body_parts import SynthPartLabeller

    _, renderer, corrections, _ = load_run_renderer(run)
    light, mean = true_light(lit_root)
    faces = None
    out = {}
    labeller = SynthPartLabeller(lit_root)
    for split in splits:
        spec = DataSpec(str(lit_root.resolve()), "synthetic", size=_size(lit_root)).open(split)
        flat = DataSpec(str(flat_root.resolve()), "synthetic", size=_size(lit_root)).open(split)
        flat_by_key = {(s.index, s.camera.name): s for s in flat}
        keys = ("learned", "true_light", "true_normals", "true_normals_light", "true_shade", "true_albedo")
        sums = {k: [] for k in keys + ("albedo_only",)}
        parts: dict = {k: {} for k in sums}
        for sample in spec:
            mask = sample.mask > 127
            gt = np.where(mask[..., None], sample.image, 0).astype(np.float64) / 255.0
            fs = flat_by_key[(sample.index, sample.camera.name)]
            if not np.array_equal(fs.mask > 127, mask):
                raise ValueError(f"flat and lit subjects differ in their masks at {sample.index}")
            gt_albedo = np.where(mask[..., None], fs.image, 0).astype(np.float64) / 255.0 * mean
            time_s = sample.time if split != "novel_pose" else None
            smpl = corrected(
                sample.smpl, (corrections or {}).get(sample.index) if split == "novel_view" else None
            )
            learned = renderer.render(sample.camera, smpl, time_s)
            albedo = renderer.render(sample.camera, smpl, time_s, light=LightSpec("albedo"))
            oracle_light = renderer.render(sample.camera, smpl, time_s, light=light)
            if faces is None:
                faces = labeller.faces
            with true_surface_normals(lit_root, sample.index, faces):
                normals_learned_light = renderer.render(sample.camera, smpl, time_s)
                normals_true_light = renderer.render(sample.camera, smpl, time_s, light=light)
            p = learned.image.astype(np.float64) / 255.0
            a = albedo.image.astype(np.float64) / 255.0
            both = (
                mask
                & (learned.alpha > 127)
                & (a.min(axis=2) > 2.0 / 255.0)
                & (gt_albedo.min(axis=2) > 2.0 / 255.0)
            )
            b3 = both[..., None]
            true_shade = np.where(b3, gt / np.maximum(gt_albedo, 1e-6), 0.0)
            learned_shade = np.where(b3, p / np.maximum(a, 1e-6), 0.0)
            images = {
                "learned": p,
                "true_light": oracle_light.image.astype(np.float64) / 255.0,
                "true_normals": normals_learned_light.image.astype(np.float64) / 255.0,
                "true_normals_light": normals_true_light.image.astype(np.float64) / 255.0,
                "true_shade": np.where(b3, np.clip(a * true_shade, 0, 1), p),
                "true_albedo": np.where(b3, np.clip(gt_albedo * learned_shade, 0, 1), p),
            }
            for k, img in images.items():
                sums[k].append(np.mean((img - gt) ** 2))
            sums["albedo_only"].append(float(np.mean((np.where(b3, a, 0) - np.where(b3, gt_albedo, 0)) ** 2)))
            regions = labeller.regions(sample.index, sample.camera)
            for k, img in images.items():
                for name, region in regions.items():
                    err = ((img - gt) ** 2)[region]
                    acc = parts[k].setdefault(name, [0.0, 0])
                    acc[0] += float(err.sum())
                    acc[1] += int(err.size)
        out[split] = {
            k: float(np.mean([10 * math.log10(1 / max(m, 1e-12)) for m in v])) for k, v in sums.items()
        }
        out[split]["parts"] = {
            k: {name: 10 * math.log10(1 / max(s / max(n, 1), 1e-12)) for name, (s, n) in d.items()}
            for k, d in parts.items()
        }
    return out


def _size(root: Path) -> int:
    from stg_node.data.synth.writer import read_metadata

    return int(max(read_metadata(root)["size"]))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", type=Path)
    p.add_argument("--lit", type=Path, required=True, help="the lit subject the run trained on")
    p.add_argument("--flat", type=Path, required=True, help="the same subject under flat light")
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    result = score(args.run, args.lit, args.flat)
    for k in result["novel_view"]:
        if k == "parts":
            continue
        nv, np_ = result["novel_view"][k], result["novel_pose"][k]
        print(f"{k:12s} NV {nv:6.2f}  NP {np_:6.2f}  gap {nv - np_:+.2f}")
    for k in result["novel_pose"]["parts"]:
        row = result["novel_pose"]["parts"][k]
        print(f"NP parts {k:12s} " + " ".join(f"{n} {v:.2f}" for n, v in row.items()))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
