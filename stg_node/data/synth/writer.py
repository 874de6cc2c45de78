"""Writes the synthetic benchmark in ZJU-MoCap's original layout, so a ZJU-MoCap loader reads it unchanged.

Layout under the output folder (``i`` = frame index, ``k`` = 1-based camera number)::

    annots.npy                  dict(cams=dict(K, D, R, T), ims=[dict(ims=[path per camera])] per frame)
    Camera_B{k}/{i:06d}.png     RGB images (PNG, lossless), black background
    mask/Camera_B{k}/{i:06d}.png        person masks, uint8 0/255
    mask_cihp/Camera_B{k}/{i:06d}.png   the same masks (hard links where the file system allows)
    new_params/{i}.npy          dict(poses (1, 72), Rh (1, 3), Th (1, 3), shapes (1, S)) float32
    new_vertices/{i}.npy        (V, 3) float32 ground-truth world vertices (garment included)
    depth/Camera_B{k}/{i:06d}.png       optional: uint16 camera-space z in millimetres, 0 = background
    synth.json                  what was generated: seed, motion, cameras, splits, rendered views

``annots.npy`` follows ZJU-MoCap exactly: ``cams`` holds one entry per camera in each of
the lists ``K`` (3, 3), ``D`` (5, 1), ``R`` (3, 3) world-to-camera and ``T`` (3, 1) in
millimetres; ``ims[i]['ims'][k]`` is the image of camera ``k`` at frame ``i`` relative to
the folder, listed for every camera at every frame as in ZJU-MoCap (so indexing by camera
works), although held-out cameras are only rendered on some frames: ``synth.json`` says
which files exist.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np

from stg_node.body.motion import save_smpl_params
from stg_node.body.params import SmplParams
from stg_node.data.synth.cameras import camera_name
from stg_node.data.types import Camera

ANNOTS_FILE = "annots.npy"
METADATA_FILE = "synth.json"
MASK_DIR = "mask"
MASK_CIHP_DIR = "mask_cihp"
PARAMS_DIR = "new_params"
VERTICES_DIR = "new_vertices"
DEPTH_DIR = "depth"
IMAGE_EXT = ".png"
PNG_COMPRESSION = 3  # zlib level: lossless either way; 3 is ~2x faster than the default 9-ish sizes
DEPTH_SCALE = 1000.0  # depth PNG units per metre (millimetres)
METADATA_FORMAT = "stg_node.synth"
METADATA_VERSION = 1


def image_relpath(camera_index: int, frame: int) -> str:
    """ZJU-MoCap relative image path: ``Camera_B{k}/{frame:06d}.png`` (camera_index is 0-based)."""
    return f"{camera_name(camera_index)}/{frame:06d}{IMAGE_EXT}"


def prepare_output(out: Path, overwrite: bool) -> Path:
    """Create ``out``; refuse a non-empty folder unless ``overwrite``, then clear only what we write."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"--out {out} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise FileExistsError(
                f"--out {out} is not empty; pass --overwrite to replace a previous benchmark there"
            )
        for child in out.iterdir():
            ours = child.name in (
                MASK_DIR,
                MASK_CIHP_DIR,
                PARAMS_DIR,
                VERTICES_DIR,
                DEPTH_DIR,
                ANNOTS_FILE,
                METADATA_FILE,
            )
            if child.is_dir() and (ours or child.name.startswith("Camera_B")):
                shutil.rmtree(child)
            elif child.is_file() and ours:
                child.unlink()
    out.mkdir(parents=True, exist_ok=True)
    return out


def write_annots(out: Path, cameras: list[Camera], num_frames: int) -> None:
    """``annots.npy`` with the cameras (T in millimetres) and every frame's image list."""
    cams = {
        "K": [np.asarray(cam.K, dtype=np.float64) for cam in cameras],
        "D": [np.zeros((5, 1)) for _ in cameras],
        "R": [np.asarray(cam.R, dtype=np.float64) for cam in cameras],
        "T": [np.asarray(cam.t, dtype=np.float64).reshape(3, 1) * 1000.0 for cam in cameras],
    }
    ims = [{"ims": [image_relpath(k, i) for k in range(len(cameras))]} for i in range(num_frames)]
    np.save(Path(out) / ANNOTS_FILE, {"cams": cams, "ims": ims}, allow_pickle=True)


def write_frame_smpl(out: Path, frame: int, params: SmplParams) -> None:
    """``new_params/{frame}.npy`` in ZJU-MoCap's dict layout (all float32, leading batch axis of 1)."""
    folder = Path(out) / PARAMS_DIR
    folder.mkdir(exist_ok=True)
    save_smpl_params(folder / f"{frame}.npy", params)


def write_frame_vertices(out: Path, frame: int, vertices: np.ndarray) -> None:
    """``new_vertices/{frame}.npy``: (V, 3) float32 world-space ground-truth vertices."""
    folder = Path(out) / VERTICES_DIR
    folder.mkdir(exist_ok=True)
    np.save(folder / f"{frame}.npy", np.asarray(vertices, dtype=np.float32))


def read_frame_vertices(folder: Path, frame: int) -> np.ndarray:
    """``new_vertices/{frame}.npy`` of a generated benchmark: (V, 3) float32 ground-truth world vertices."""
    from stg_node.data.errors import DatasetError
    from stg_node.safe_load import load_npy

    path = Path(folder) / VERTICES_DIR / f"{frame}.npy"
    if not path.is_file():
        raise DatasetError(
            path, "is missing", f"the ground-truth vertices stg-synth writes for frame {frame}"
        )
    vertices = np.asarray(load_npy(path))
    if vertices.ndim != 2 or vertices.shape[1] != 3 or not np.isfinite(vertices).all():
        raise DatasetError(path, f"holds an array of shape {vertices.shape}", "finite (V, 3) vertices")
    return vertices.astype(np.float32, copy=False)


def _imwrite(path: Path, array: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), array, [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION]):
        raise OSError(f"could not write {path}")


def write_view(
    out: Path,
    camera_index: int,
    frame: int,
    image: np.ndarray,
    mask: np.ndarray,
    depth: np.ndarray | None = None,
) -> None:
    """One rendered view: image, mask (and its mask_cihp twin), optionally depth in millimetres."""
    out = Path(out)
    rel = image_relpath(camera_index, frame)
    _imwrite(out / rel, cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    mask_path = out / MASK_DIR / rel
    _imwrite(mask_path, mask)
    cihp_path = out / MASK_CIHP_DIR / rel
    cihp_path.parent.mkdir(parents=True, exist_ok=True)
    if cihp_path.exists():
        cihp_path.unlink()
    try:
        os.link(mask_path, cihp_path)
    except OSError:
        shutil.copyfile(mask_path, cihp_path)
    if depth is not None:
        millimetres = np.clip(np.round(np.asarray(depth, dtype=np.float64) * DEPTH_SCALE), 0, 65535)
        _imwrite(out / DEPTH_DIR / rel, millimetres.astype(np.uint16))


def write_metadata(out: Path, metadata: dict) -> None:
    """``synth.json``: the generator's record of what it wrote (see docs/SYNTH.md)."""
    record = {"format": METADATA_FORMAT, "version": METADATA_VERSION, **metadata}
    (Path(out) / METADATA_FILE).write_text(json.dumps(record, indent=1, sort_keys=False) + "\n")


def read_metadata(folder: Path) -> dict:
    """Read and check ``synth.json`` of a generated benchmark."""
    path = Path(folder) / METADATA_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: {folder} is not a stg-synth benchmark folder")
    try:
        record = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path} is not valid JSON: {err}") from None
    if record.get("format") != METADATA_FORMAT:
        raise ValueError(f"{path} has format {record.get('format')!r}, expected {METADATA_FORMAT!r}")
    if record.get("version") != METADATA_VERSION:
        raise ValueError(
            f"{path} has version {record.get('version')!r}; this reader knows {METADATA_VERSION}"
        )
    return record
