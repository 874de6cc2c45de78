"""THuman4.0 (Zheng et al., CVPR 2022): 24 calibrated cameras at 30 fps, one used as monocular input.

Layout, from the dataset's Readme (ZhengZerong/THUman4.0-Dataset) and the loader of
AnimatableGaussians (same lab)::

    subject00/
      calibration.json         {"cam00": {"K": 3x3, "R": 3x3, "T": [3] (metres), "imgSize": [w, h]}, ...}
      images/cam00/00000000.jpg
      masks/cam00/00000000.jpg BackgroundMattingV2 alpha as JPEG; > 128 is the person
      smpl_params.npz          SMPL-X: global_orient, transl, body_pose (63), betas, jaw_pose, expression,
                               left/right_hand_pose; one row per frame (betas may have one row)
      missing_img_files.txt    views lost during capture (optional), e.g. images\\cam03\\00000123.jpg

Not confirmed by the Readme (said in docs/DATASETS.md): whether ``calibration.json`` carries
distortion (we read ``D``/``dist``/``distCoeff`` when present and assume none otherwise, as
both public readers do), and the order of ``imgSize`` (we take [width, height] as
AnimatableGaussians does, and check it against the first image).

The fits are SMPL-X. :class:`SmplParams` gets ``model="smplx"``: the 21 body joints and the
global orientation map onto SMPL's first 22 joints; SMPL's two hand joints are zero; the SMPL-X
``betas`` are passed through but live in SMPL-X's shape space, not SMPL's.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from stg_node.data.base import SequenceDataset, image_size, smpl_from_arrays
from stg_node.data.errors import DatasetError
from stg_node.data.io import as_array, as_size, load_json, load_npz_arrays
from stg_node.data.splits import FrameRange, MonocularProtocol, SplitSpec
from stg_node.data.types import SmplParams
from stg_node.data.views import RawCamera

log = logging.getLogger(__name__)

THUMAN4_FPS = 30.0  # stated in the dataset Readme
SMPLX_KEYS = ("global_orient", "transl", "body_pose", "betas")


class THuman4Dataset(SequenceDataset):
    kind = "thuman4"

    def __init__(
        self,
        root: str | Path,
        split: str | SplitSpec = "train",
        *,
        size=512,
        fps: float = THUMAN4_FPS,
        train_camera: str = "cam00",
        train_frames: FrameRange | None = None,
    ):
        protocol = MonocularProtocol(
            train_camera, train_frames or FrameRange(), "ours: THuman4.0 has no published monocular protocol"
        )
        super().__init__(root, split, size=size, fps=fps, protocol=protocol)

    def _index(self) -> None:
        calib_path = self.root / "calibration.json"
        calib = load_json(calib_path)
        if not isinstance(calib, dict) or not calib:
            raise DatasetError(
                calib_path, "is not a non-empty object", '{"cam00": {"K", "R", "T", "imgSize"}, ...}'
            )
        for name, entry in calib.items():
            if not isinstance(entry, dict):
                raise DatasetError(
                    calib_path,
                    f"camera {name!r} is {type(entry).__name__}, not an object",
                    '{"K", "R", "T", "imgSize"}',
                )
        self._calib = calib
        self.all_camera_names = sorted(calib)
        params_path = self.root / "smpl_params.npz"
        arrays = load_npz_arrays(params_path, "SMPL-X parameters per frame (smpl_params.npz)")
        params = {}
        for key, value in arrays.items():
            try:
                params[key] = np.asarray(value, dtype=np.float64)
            except (TypeError, ValueError) as exc:
                raise DatasetError(params_path, f"{key} is not numeric ({exc})", "float arrays") from exc
        missing = [k for k in SMPLX_KEYS if k not in params]
        if missing:
            raise DatasetError(params_path, f"lacks {missing}", f"arrays {list(SMPLX_KEYS)}")
        for key in SMPLX_KEYS:
            if params[key].ndim < 1 or params[key].size == 0:
                raise DatasetError(
                    params_path, f"{key} has shape {params[key].shape}", f"{key}: one row per frame"
                )
        count = len(params["global_orient"])
        for key in ("transl", "body_pose"):
            if len(params[key]) != count:
                raise DatasetError(
                    params_path,
                    f"{key} has {len(params[key])} rows but global_orient {count}",
                    "one row per frame in every per-frame array",
                )
        if params["body_pose"].reshape(count, -1).shape[1] != 63:
            raise DatasetError(
                params_path,
                f"body_pose has {params['body_pose'].reshape(count, -1).shape[1]} values per frame",
                "63 (21 SMPL-X body joints x 3)",
            )
        self._params = params
        self._params_path = params_path
        self.all_frames = list(range(count))
        for folder in ("images", "masks"):
            if not (self.root / folder).is_dir():
                raise DatasetError(self.root / folder, "folder is missing", f"{folder}/camXX/%08d.jpg")
        self._missing: set[tuple[int, str]] = set()
        missing_list = self.root / "missing_img_files.txt"
        if missing_list.is_file():
            for line in missing_list.read_text().splitlines():
                parts = re.split(r"[\\/]", line.strip())
                if len(parts) >= 2 and parts[-1][:-4].isdigit():
                    self._missing.add((int(parts[-1][:-4]), parts[-2]))

    def _has_view(self, frame: int, camera: str) -> bool:
        return (frame, camera) not in self._missing

    def _raw_camera(self, name: str) -> RawCamera:
        where = self.root / "calibration.json"
        entry = self._calib[name]
        for key in ("K", "R", "T"):
            if key not in entry:
                raise DatasetError(where, f"camera {name} lacks {key}", "K, R, T (and imgSize) per camera")
        K = as_array(entry["K"], (3, 3), path=where, name=f"{name}.K")
        R = as_array(entry["R"], (3, 3), path=where, name=f"{name}.R")
        T = as_array(entry["T"], (3,), path=where, name=f"{name}.T")
        dist = next((entry[k] for k in ("D", "dist", "distCoeff", "distortion") if k in entry), None)
        D = np.zeros(5) if dist is None else as_array(dist, (np.size(dist),), path=where, name=f"{name}.D")
        first = next((f for f in self.all_frames if self._has_view(f, name)), self.all_frames[0])
        width, height = image_size(self.image_path(first, name))
        size = entry.get("imgSize")
        if size is not None and (not isinstance(size, list) or len(size) != 2):
            raise DatasetError(where, f"camera {name} imgSize is {size!r}", "imgSize = [width, height]")
        if size is not None and [as_size(v, path=where, name=f"{name}.imgSize") for v in size] != [
            width,
            height,
        ]:
            raise DatasetError(
                where,
                f"camera {name} imgSize {entry['imgSize']} but its images are {width}x{height}",
                "imgSize = [width, height] of the camera's images",
            )
        return RawCamera(name=name, K=K, D=D, R=R, t=T, width=width, height=height)

    def image_path(self, frame: int, camera: str) -> Path:
        return self.root / "images" / camera / f"{frame:08d}.jpg"

    def mask_path(self, frame: int, camera: str) -> Path:
        return self.root / "masks" / camera / f"{frame:08d}.jpg"

    def _read_smpl(self, frame: int) -> SmplParams:
        p = self._params
        poses = np.zeros((24, 3))
        poses[0] = p["global_orient"][frame].reshape(3)
        poses[1:22] = p["body_pose"][frame].reshape(21, 3)
        betas = p["betas"].reshape(-1, p["betas"].shape[-1])
        betas = betas[frame] if len(betas) > 1 else betas[0]
        where = f"{self._params_path} (frame {frame})"
        return smpl_from_arrays(
            poses=poses, Rh=np.zeros(3), Th=p["transl"][frame], betas=betas, path=where, model="smplx"
        )
