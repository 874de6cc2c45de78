"""ZJU-MoCap in its two layouts: the original release and the refined ``my_XXX`` one.

Original (Neural Body's release, also what ``stg-synth`` writes)::

    CoreView_377/
      annots.npy            {'cams': {'K','D','R','T' (mm)}, 'ims': [{'ims': [path per camera]}, ...]}
      Camera_B1/000000.jpg  ('Camera (1)/CoreView_313_Camera_(1)_0001_<date>.jpg' for 313 and 315)
      mask_cihp/Camera_B1/000000.png   and/or  mask/Camera_B1/000000.png (any non-zero = person)
      new_params/0.npy      {'poses' (1, 72), 'Rh' (1, 3), 'Th' (1, 3), 'shapes' (1, 10)}

Refined (the re-calibrated release used by GauHuman and 3DGS-Avatar's ``refine`` option)::

    my_377/
      annots.npy            same keys; 'ims' paths like 'images/00/000000.jpg'
      images/00/000000.jpg  mask/00/000000.png  smpl_params/0.npy  smpl_vertices/0.npy

Frames are numbered by their position in ``annots['ims']``; the SMPL file of a frame is found
from its image name (``000123.jpg`` -> ``123.npy``; for 313/315 the fifth ``_`` field, which is
1-based). Cameras are named by their number as in the papers: ``Camera_B1`` -> ``"1"``; refined
folder ``00`` -> ``"1"``, so one split table serves both layouts.
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from stg_node.data.base import SequenceDataset, image_size, smpl_from_arrays
from stg_node.data.errors import DatasetError
from stg_node.data.io import as_array, as_distortion, find_image, load_npy_dict, read_mask
from stg_node.data.splits import FrameRange, MonocularProtocol, SplitSpec, zju_protocol
from stg_node.data.types import SmplParams
from stg_node.data.views import RawCamera

log = logging.getLogger(__name__)

# ZJU-MoCap's frame rate is not stated in its release notes; 50 fps is what we assume for
# FrameSample.time (see docs/DATASETS.md). Pass fps= to override.
ZJU_FPS = 50.0
MASK_SOURCES = ("auto", "mask_cihp", "mask", "union")


def _camera_number(folder: str) -> int | None:
    digits = re.findall(r"\d+", folder)
    return int(digits[-1]) if digits else None


def _params_number(image_rel: str) -> int:
    """The SMPL file number of an image: its digit stem, or the 313/315 '_'-field."""
    stem = PurePosixPath(image_rel).stem
    if stem.isdigit():
        return int(stem)
    fields = stem.split("_")
    if len(fields) > 4 and fields[4].isdigit():
        return int(fields[4])
    raise ValueError(stem)


class ZJUMoCapDataset(SequenceDataset):
    """A ZJU-MoCap subject in the original or refined layout (``refined`` chosen from the files)."""

    kind = "zju"

    def __init__(
        self,
        root: str | Path,
        split: str | SplitSpec = "train",
        *,
        size=512,
        fps: float = ZJU_FPS,
        train_camera: str = "1",
        mask_source: str = "auto",
        subject: str | None = None,
        train_frames: FrameRange | None = None,
    ):
        """``subject`` picks the split table row (default: the folder name, e.g. 'CoreView_377');
        ``train_frames`` overrides its training range (the test splits follow from it)."""
        if mask_source not in MASK_SOURCES:
            raise ValueError(f"mask_source must be one of {MASK_SOURCES}, got {mask_source!r}")
        self.mask_source = mask_source
        root = Path(root)
        self.subject = subject or root.name
        protocol = zju_protocol(self.subject, train_camera)
        if train_frames is not None:
            protocol = MonocularProtocol(train_camera, train_frames, "train_frames given by the caller")
        super().__init__(root, split, size=size, fps=fps, protocol=protocol)

    # --- index ----------------------------------------------------------------------------
    def _index(self) -> None:
        root = self.root
        self.refined = (root / "smpl_params").is_dir() and (root / "images").is_dir()
        annots_path = root / "annots.npy"
        annots = load_npy_dict(annots_path)
        cams, ims = annots.get("cams"), annots.get("ims")
        if not isinstance(cams, dict) or not all(k in cams for k in "KDRT"):
            raise DatasetError(
                annots_path,
                "has no 'cams' dict with K, D, R, T",
                "annots['cams'] = {'K': [...], 'D': [...], 'R': [...], 'T': [...]}",
            )
        counts = {k: len(cams[k]) for k in "KDRT"}
        if len(set(counts.values())) != 1:
            raise DatasetError(
                annots_path, f"camera lists differ in length {counts}", "one K, D, R, T per camera"
            )
        num_cams = counts["K"]
        if not isinstance(ims, list | tuple | np.ndarray) or len(ims) == 0:
            raise DatasetError(
                annots_path, "has no 'ims' list", "annots['ims'] = [{'ims': [path per camera]}, ...]"
            )
        rel_paths: list[list[str]] = []
        for position, entry in enumerate(ims):
            paths = entry.get("ims") if isinstance(entry, dict) else None
            if paths is None or len(paths) != num_cams:
                got = "no 'ims' key" if paths is None else f"{len(paths)} image paths"
                raise DatasetError(
                    annots_path, f"frame {position} has {got}", f"{num_cams} paths, one per camera"
                )
            rel_paths.append([str(p).replace("\\", "/") for p in paths])

        # Camera names from the folders of frame 0 ('Camera_B3' -> '3'; refined '02' -> '3').
        names = []
        for index, rel in enumerate(rel_paths[0]):
            folder = PurePosixPath(rel).parent.name
            number = _camera_number(folder)
            if number is None:
                raise DatasetError(
                    annots_path,
                    f"camera {index} image path {rel!r} has no camera number",
                    "paths like 'Camera_B1/000000.jpg' or 'images/00/000000.jpg'",
                )
            names.append(str(number + 1 if self.refined else number))
        if len(set(names)) != len(names):
            raise DatasetError(
                annots_path, f"camera folders give duplicate names {names}", "one folder per camera"
            )

        self._cams_raw = cams
        self._cam_index = {name: i for i, name in enumerate(names)}
        self._rel_paths = rel_paths
        self.all_camera_names = names

        self._params_dir = self._find_params_dir()
        present = {
            int(f[:-4]) for f in os.listdir(self._params_dir) if f.endswith(".npy") and f[:-4].isdigit()
        }
        self._params_number: dict[int, int] = {}
        frames, missing = [], 0
        for position, paths in enumerate(rel_paths):
            try:
                number = _params_number(paths[0])
            except ValueError:
                raise DatasetError(
                    annots_path,
                    f"frame {position} image name {paths[0]!r} has no frame number",
                    "'000123.jpg' or the 313/315 naming",
                ) from None
            if number in present:
                self._params_number[position] = number
                frames.append(position)
            else:
                missing += 1
        if missing:
            log.warning(
                "%s: %d of %d frames have no SMPL file in %s; they are skipped",
                root,
                missing,
                len(rel_paths),
                self._params_dir.name,
            )
        if not frames:
            raise DatasetError(
                self._params_dir,
                "holds no SMPL file for any frame of annots.npy",
                "files <n>.npy named after the image numbers",
            )
        self.all_frames = frames
        self._mask_root = None if self.refined else self._find_mask_root()

    def _find_params_dir(self) -> Path:
        candidates = ["smpl_params"] if self.refined else ["new_params", "params"]
        for name in candidates:
            if (self.root / name).is_dir():
                return self.root / name
        raise DatasetError(
            self.root / candidates[0],
            "SMPL parameter folder is missing",
            f"one of {candidates} with <frame>.npy files",
        )

    def _find_mask_root(self) -> list[Path]:
        have = {name: (self.root / name).is_dir() for name in ("mask_cihp", "mask")}
        if self.mask_source == "auto":
            chosen = ["mask_cihp"] if have["mask_cihp"] else ["mask"] if have["mask"] else []
        elif self.mask_source == "union":
            chosen = ["mask", "mask_cihp"]
        else:
            chosen = [self.mask_source]
        for name in chosen:
            if not have[name]:
                raise DatasetError(
                    self.root / name, "mask folder is missing", "mask_cihp/ or mask/ beside annots.npy"
                )
        if not chosen:
            raise DatasetError(
                self.root / "mask_cihp", "no mask folder", "mask_cihp/ or mask/ beside annots.npy"
            )
        return [self.root / name for name in chosen]

    # --- cameras ---------------------------------------------------------------------------
    def _raw_camera(self, name: str) -> RawCamera:
        i = self._cam_index[name]
        where = self.root / "annots.npy"
        K = as_array(self._cams_raw["K"][i], (3, 3), path=where, name=f"cams['K'][{i}]")
        D = as_distortion(self._cams_raw["D"][i], path=where, name=f"cams['D'][{i}]")
        R = as_array(self._cams_raw["R"][i], (3, 3), path=where, name=f"cams['R'][{i}]")
        T = as_array(self._cams_raw["T"][i], (3,), path=where, name=f"cams['T'][{i}]") / 1000.0  # mm -> m
        if abs(np.linalg.det(R) - 1.0) > 1e-3:
            raise DatasetError(
                where,
                f"cams['R'][{i}] is not a rotation (det {np.linalg.det(R):.4f})",
                "an orthonormal 3x3 matrix",
            )
        width, height = image_size(self.image_path(self.all_frames[0], name))
        return RawCamera(name=name, K=K, D=D, R=R, t=T, width=width, height=height)

    # --- files -----------------------------------------------------------------------------
    def _rel(self, frame: int, camera: str) -> str:
        return self._rel_paths[frame][self._cam_index[camera]]

    def image_path(self, frame: int, camera: str) -> Path:
        return self.root / self._rel(frame, camera)

    def mask_path(self, frame: int, camera: str) -> Path:
        return self.mask_paths(frame, camera)[0]

    def mask_paths(self, frame: int, camera: str) -> list[Path]:
        rel = PurePosixPath(self._rel(frame, camera))
        if self.refined:
            parts = list(rel.parts)
            parts[0] = "mask" if parts[0] == "images" else parts[0]
            stems = [self.root.joinpath(*parts).with_suffix("")]
        else:
            stems = [root / rel.with_suffix("") for root in self._mask_root]
        paths = []
        for stem in stems:
            found = find_image(stem)
            paths.append(found if found is not None else stem.with_suffix(".png"))
        return paths

    def read_view_mask(self, frame: int, camera: str) -> tuple[np.ndarray, Path]:
        if self.refined or len(self._mask_root) == 1:
            return super().read_view_mask(frame, camera)
        # union of mask/ and mask_cihp/, as Neural Body's can_smpl loader does
        paths = self.mask_paths(frame, camera)
        return np.maximum.reduce([read_mask(p) for p in paths]), paths[0]

    def smpl_path(self, frame: int) -> Path:
        if frame not in self._params_number:
            raise DatasetError(
                self._params_dir,
                f"frame {frame} has no SMPL parameters",
                f"a frame of this sequence with its <n>.npy file (frames {self.all_frames[0]}.."
                f"{self.all_frames[-1]})",
            )
        return self._params_dir / f"{self._params_number[frame]}.npy"

    def _read_smpl(self, frame: int) -> SmplParams:
        path = self.smpl_path(frame)
        params: dict[str, Any] = load_npy_dict(path)
        missing = [k for k in ("poses", "Rh", "Th", "shapes") if k not in params]
        if missing:
            raise DatasetError(path, f"lacks {missing}", "a dict with poses, Rh, Th, shapes")
        return smpl_from_arrays(
            poses=params["poses"], Rh=params["Rh"], Th=params["Th"], betas=params["shapes"], path=path
        )
