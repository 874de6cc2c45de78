"""The folder format for a user's own capture: plain files anyone can produce.

::

    capture/
      cameras.json   {"fps": 30, "cameras": {"front": {"K": 3x3, "R": 3x3, "t": [3] metres,
                                                       "D": [k1, k2, p1, p2, k3] (optional),
                                                       "width": W, "height": H}}}
      images/front/000000.jpg ...   (one folder per camera; with a single camera, images/*.jpg works too)
      masks/front/000000.png ...    (same names, any image type; non-zero = person, JPEG: >= 128)
      poses.npz      poses (N, 72) or (N, 24, 3); Th (N, 3); Rh (N, 3) optional (zeros);
                     betas (10,) or (N, 10); optional frames (N,) frame numbers, times (N,) seconds

Frame numbers are the digits of the image names; row ``i`` of poses.npz belongs to the ``i``-th
frame in sorted order, unless ``frames`` lists the frame number of each row. Every camera must
have an image and a mask for every frame. docs/DATASETS.md says how to produce each file.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from stg_node.data.base import SequenceDataset, smpl_from_arrays
from stg_node.data.errors import DatasetError
from stg_node.data.io import (
    IMAGE_SUFFIXES,
    as_array,
    as_distortion,
    as_rows,
    as_size,
    load_json,
    load_npz_arrays,
)
from stg_node.data.splits import FrameRange, MonocularProtocol, SplitSpec
from stg_node.data.types import SmplParams
from stg_node.data.views import RawCamera

DEFAULT_FPS = 30.0


def _frame_number(path: Path) -> int | None:
    digits = re.findall(r"\d+", path.stem)
    return int(digits[-1]) if digits else None


def _list_images(folder: Path) -> dict[int, Path]:
    found: dict[int, Path] = {}
    for path in sorted(folder.iterdir()):
        if path.suffix.lower() not in IMAGE_SUFFIXES or not path.is_file():
            continue
        number = _frame_number(path)
        if number is None:
            raise DatasetError(path, "image name has no frame number", "names like 000123.jpg")
        if number in found:
            raise DatasetError(
                path, f"frame number {number} also used by {found[number].name}", "one file per frame"
            )
        found[number] = path
    return found


class FolderDataset(SequenceDataset):
    kind = "folder"

    def __init__(
        self,
        root: str | Path,
        split: str | SplitSpec = "train",
        *,
        size=512,
        fps: float | None = None,
        train_camera: str | None = None,
        train_frames: FrameRange | None = None,
    ):
        self._fps_arg = fps
        self._train_camera = train_camera
        self._train_frames = train_frames or FrameRange()
        super().__init__(root, split, size=size, fps=fps or DEFAULT_FPS)

    def _index(self) -> None:
        cameras_path = self.root / "cameras.json"
        doc = load_json(cameras_path)
        cams = doc.get("cameras") if isinstance(doc, dict) else None
        if not isinstance(cams, dict) or not cams:
            raise DatasetError(
                cameras_path, "has no 'cameras' object", '{"cameras": {"name": {"K", "R", "t", ...}}}'
            )
        for name, entry in cams.items():
            if not isinstance(entry, dict):
                raise DatasetError(
                    cameras_path,
                    f"camera {name!r} is {type(entry).__name__}, not an object",
                    '{"K", "R", "t", ...}',
                )
        self._cams = cams
        self.all_camera_names = list(cams)
        if self._fps_arg is None and "fps" in doc:
            fps = as_array(doc["fps"], (1,), path=cameras_path, name="fps")[0]
            if fps <= 0:
                raise DatasetError(cameras_path, f"fps is {fps}", "a positive frame rate")
            self.fps = float(fps)

        single = len(cams) == 1
        self._images: dict[str, dict[int, Path]] = {}
        self._masks: dict[str, dict[int, Path]] = {}
        for kind, store in (("images", self._images), ("masks", self._masks)):
            base = self.root / kind
            if not base.is_dir():
                raise DatasetError(base, "folder is missing", f"{kind}/<camera>/<frame>.jpg|png")
            for name in cams:
                folder = base / name
                if not folder.is_dir():
                    if single:
                        folder = base
                    else:
                        raise DatasetError(
                            folder,
                            f"folder for camera {name!r} is missing",
                            f"one {kind}/<camera>/ folder per camera in cameras.json",
                        )
                store[name] = _list_images(folder)
                if not store[name]:
                    raise DatasetError(folder, f"holds no {kind}", ".jpg/.png files named by frame number")
        frames = sorted(self._images[self.all_camera_names[0]])
        for name in cams:
            for kind, store in (("images", self._images), ("masks", self._masks)):
                have = sorted(store[name])
                if have != frames:
                    extra = sorted(set(have) - set(frames))[:5]
                    lacking = sorted(set(frames) - set(have))[:5]
                    folder = self.root / kind / name
                    raise DatasetError(
                        folder,
                        f"{len(have)} {kind} for camera {name!r} vs {len(frames)} frames "
                        f"(extra frames {extra}, missing frames {lacking})",
                        "the same frame numbers for every camera's images and masks",
                    )
        self._load_poses(frames)

    def _load_poses(self, frames: list[int]) -> None:
        path = self.root / "poses.npz"
        data = load_npz_arrays(path, "SMPL parameters per frame (poses, Th, betas)")
        if "Th" not in data and "transl" in data:
            data["Th"] = data["transl"]
        if "betas" not in data and "shapes" in data:
            data["betas"] = data["shapes"]
        missing = [k for k in ("poses", "Th", "betas") if k not in data]
        if missing:
            raise DatasetError(path, f"lacks {missing}", "arrays poses (N, 72), Th (N, 3), betas (10,)")
        for key in ("poses", "Th", "Rh", "betas", "frames", "times"):
            if key in data:
                data[key] = as_rows(data[key], path=path, name=key)
        count = len(data["poses"])
        rows = data.get("frames")
        if rows is not None:
            rows = [int(v) for v in np.asarray(rows).reshape(-1)]
            if len(rows) != count:
                raise DatasetError(
                    path, f"frames has {len(rows)} entries but poses {count} rows", "one per row"
                )
            absent = sorted(set(frames) - set(rows))[:5]
            if absent:
                raise DatasetError(path, f"has no pose for frames {absent}", "a row for every image's frame")
        else:
            if count != len(frames):
                raise DatasetError(
                    path,
                    f"has {count} pose rows but images/ has {len(frames)} frames",
                    "one row per frame (or a 'frames' array naming each row's frame)",
                )
            rows = frames
        betas = data["betas"]
        if betas.ndim == 2 and len(betas) != count:
            raise DatasetError(
                path, f"betas has {len(betas)} rows but poses {count}", "(S,) or one row per frame"
            )
        for key in ("Th", "Rh"):
            if key in data and len(data[key]) != count:
                raise DatasetError(
                    path, f"{key} has {len(data[key])} rows but poses {count}", "one row per frame"
                )
        self._row = {frame: i for i, frame in enumerate(rows)}
        self._poses = data
        self._poses_path = path
        self.all_frames = frames
        if "times" in data:
            times = as_array(data["times"], (count,), path=path, name="times")
            self._times = {
                frame: float(times[self._row[frame]] - times[self._row[frames[0]]]) for frame in frames
            }
        else:
            self._times = None

    @property
    def protocol(self) -> MonocularProtocol:  # type: ignore[override]
        camera = self._train_camera or self.all_camera_names[0]
        return MonocularProtocol(
            camera, self._train_frames, "folder: first camera in cameras.json, every frame"
        )

    def _raw_camera(self, name: str) -> RawCamera:
        where = self.root / "cameras.json"
        entry = self._cams[name]
        for key in ("K", "R", "t", "width", "height"):
            if key not in entry:
                raise DatasetError(
                    where, f"camera {name!r} lacks {key!r}", "K, R, t, width, height (D optional)"
                )
        D = as_distortion(entry.get("D", np.zeros(5)), path=where, name=f"{name}.D")
        return RawCamera(
            name=name,
            K=as_array(entry["K"], (3, 3), path=where, name=f"{name}.K"),
            D=D,
            R=as_array(entry["R"], (3, 3), path=where, name=f"{name}.R"),
            t=as_array(entry["t"], (3,), path=where, name=f"{name}.t"),
            width=as_size(entry["width"], path=where, name=f"{name}.width"),
            height=as_size(entry["height"], path=where, name=f"{name}.height"),
        )

    def image_path(self, frame: int, camera: str) -> Path:
        return self._images[camera][frame]

    def mask_path(self, frame: int, camera: str) -> Path:
        return self._masks[camera][frame]

    def time(self, frame: int) -> float:
        if self._times is not None:
            return self._times[frame]
        return super().time(frame)

    def _read_smpl(self, frame: int) -> SmplParams:
        i = self._row[frame]
        d = self._poses
        betas = np.asarray(d["betas"], dtype=np.float64)
        betas = betas[i] if betas.ndim == 2 else betas
        Rh = d["Rh"][i] if "Rh" in d else np.zeros(3)
        return smpl_from_arrays(
            poses=d["poses"][i],
            Rh=Rh,
            Th=d["Th"][i],
            betas=betas,
            path=f"{self._poses_path} (row {i}, frame {frame})",
        )
