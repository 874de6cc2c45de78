"""The lazy, split-aware dataset every loader builds on: views listed at open, pixels read on access.

A subclass says where things are (cameras, image and mask paths, SMPL parameters per frame);
this class turns that into an indexable sequence of :class:`~stg_node.data.types.FrameSample`
for one split, with per-camera undistortion/resizing (:mod:`stg_node.data.views`) and SMPL
parameters checked for shape and NaN.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
from PIL import Image

from stg_node.body.params import LIMITS, magnitude_problem
from stg_node.data.errors import DatasetError
from stg_node.data.io import as_array, read_image, read_mask
from stg_node.data.splits import MonocularProtocol, SplitSpec
from stg_node.data.types import Camera, FrameSample, SmplParams
from stg_node.data.views import RawCamera, ViewPreparer

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ViewRef:
    """One view of a split: frame position in the sequence and camera name."""

    frame: int
    camera: str


def image_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` from the file header, without decoding the pixels."""
    if not path.is_file():
        raise DatasetError(path, "image file is missing", "an existing image to take the camera's size from")
    try:
        with Image.open(path) as img:
            return img.size
    except Exception as exc:  # PIL raises UnidentifiedImageError, OSError ...
        raise DatasetError(path, f"cannot be read as an image ({exc})", "a readable JPEG/PNG") from exc


def smpl_from_arrays(*, poses, Rh, Th, betas, path, model: str = "smpl") -> SmplParams:
    """Validated :class:`SmplParams`: poses (24, 3) (72 values, or more: SMPL-H/X extras dropped)."""
    poses = np.asarray(as_array(poses, (np.size(poses),), path=path, name="poses")).reshape(-1)
    if poses.size < 72:
        raise DatasetError(path, f"poses has {poses.size} values", "72 (24 joints x 3 axis-angle)")
    poses = as_array(poses[:72], (24, 3), path=path, name="poses")
    Rh = as_array(Rh, (3,), path=path, name="Rh")
    Th = as_array(Th, (3,), path=path, name="Th")
    betas = as_array(betas, (np.size(betas),), path=path, name="shapes/betas")
    if betas.size == 0:
        raise DatasetError(path, "shapes/betas is empty", "at least one shape coefficient")
    for name, value in (("poses", poses), ("Rh", Rh), ("Th", Th), ("betas", betas)):
        problem = magnitude_problem(name, value)
        if problem:
            raise DatasetError(path, problem, f"{name} within +-{LIMITS[name]:g}")
    return SmplParams(
        poses=poses.astype(np.float32),
        Rh=Rh.astype(np.float32),
        Th=Th.astype(np.float32),
        betas=betas.astype(np.float32),
        model=model,
    )


class SequenceDataset(Sequence[FrameSample], ABC):
    """Views of one split of a calibrated sequence, loaded lazily by index."""

    kind = "base"

    def __init__(
        self,
        root: str | Path,
        split: str | SplitSpec = "train",
        *,
        size: int | tuple[int, int] | None = 512,
        fps: float = 30.0,
        protocol: MonocularProtocol | None = None,
    ):
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(self.root, "dataset folder does not exist", "a folder")
        self.size = size
        self.fps = float(fps)
        self._protocol = protocol
        self._preparers: dict[str, ViewPreparer] = {}
        self._index()
        spec = split if isinstance(split, SplitSpec) else self.protocol.split(split)
        self.split = spec
        cams, positions = spec.resolve(self.all_camera_names, len(self.all_frames), where=str(self.root))
        frames = [self.all_frames[p] for p in positions]
        self._frames = frames
        self._cameras = cams
        views = [ViewRef(frame, cam) for frame in frames for cam in cams]
        self._views = [v for v in views if self._has_view(v.frame, v.camera)]
        if len(self._views) < len(views):
            log.warning(
                "%s: %d of %d views of split %r are listed as missing and skipped",
                self.root,
                len(views) - len(self._views),
                len(views),
                spec.name,
            )
        if not self._views:
            raise DatasetError(self.root, f"split {spec.name!r} has no view left", "at least one image")
        log.debug(
            "%s %s split %r: %d frames x %d cameras", self.kind, self.root, spec.name, len(frames), len(cams)
        )

    # --- what subclasses provide -------------------------------------------------------------
    @abstractmethod
    def _index(self) -> None:
        """Read the index files (annotations, calibration); set ``all_camera_names`` and ``all_frames``."""

    @abstractmethod
    def _raw_camera(self, name: str) -> RawCamera: ...

    @abstractmethod
    def image_path(self, frame: int, camera: str) -> Path: ...

    @abstractmethod
    def mask_path(self, frame: int, camera: str) -> Path: ...

    @abstractmethod
    def _read_smpl(self, frame: int) -> SmplParams: ...

    def _has_view(self, frame: int, camera: str) -> bool:
        """False for views the dataset itself lists as lost (THuman4.0's missing_img_files.txt)."""
        return True

    all_camera_names: list[str]
    all_frames: list[int]  # frame numbers of the sequence, in order (split positions index this list)

    @cached_property
    def protocol(self) -> MonocularProtocol:
        from stg_node.data.splits import FrameRange

        if self._protocol is not None:
            return self._protocol
        return MonocularProtocol(self.all_camera_names[0], FrameRange(), "default: first camera, every frame")

    # --- the public sequence -----------------------------------------------------------------
    @property
    def views(self) -> list[ViewRef]:
        return list(self._views)

    @property
    def frames(self) -> list[int]:
        """Frame numbers in this split, in order."""
        return list(self._frames)

    @property
    def camera_names(self) -> list[str]:
        """Cameras in this split."""
        return list(self._cameras)

    def __len__(self) -> int:
        return len(self._views)

    def __getitem__(self, index):  # type: ignore[override]
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        ref = self._views[index]
        return self.load(ref.frame, ref.camera)

    def __iter__(self) -> Iterator[FrameSample]:
        for ref in self._views:
            yield self.load(ref.frame, ref.camera)

    def preparer(self, name: str) -> ViewPreparer:
        if name not in self._preparers:
            if name not in self.all_camera_names:
                raise KeyError(f"no camera {name!r} in {self.root}; cameras: {self.all_camera_names}")
            self._preparers[name] = ViewPreparer(self._raw_camera(name), self.size)
        return self._preparers[name]

    def camera(self, name: str) -> Camera:
        """The delivered camera (after undistortion and resizing)."""
        return self.preparer(name).camera

    def smpl(self, frame: int) -> SmplParams:
        return self._read_smpl(frame)

    def time(self, frame: int) -> float:
        """Seconds since the first frame of the sequence."""
        return (frame - self.all_frames[0]) / self.fps

    def read_view_mask(self, frame: int, camera: str) -> tuple[np.ndarray, Path]:
        """The raw ``(H, W)`` uint8 mask of a view and the file to name in errors (a loader that
        combines several mask files overrides this)."""
        path = self.mask_path(frame, camera)
        return read_mask(path), path

    def load(self, frame: int, camera: str) -> FrameSample:
        image_path = self.image_path(frame, camera)
        mask, mask_path = self.read_view_mask(frame, camera)
        preparer = self.preparer(camera)
        image, mask = preparer(read_image(image_path), mask, image_path=image_path, mask_path=mask_path)
        return FrameSample(
            index=frame,
            time=self.time(frame),
            image=image,
            mask=mask,
            camera=preparer.camera,
            smpl=self.smpl(frame),
        )

    def check(self) -> int:
        """Verify that every view of the split has its image, mask and SMPL file; returns the count.

        Only looks at file presence and SMPL contents, not at pixels; ``open_dataset(check=True)``
        runs it so a missing file fails at open, not hours into training.
        """
        for frame in self._frames:
            self.smpl(frame)
        for ref in self._views:
            for path in (self.image_path(ref.frame, ref.camera), self.mask_path(ref.frame, ref.camera)):
                if not path.is_file():
                    raise DatasetError(
                        path,
                        f"missing for frame {ref.frame}, camera {ref.camera}",
                        "an image and a mask for every view of the split",
                    )
        return len(self._views)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}({str(self.root)!r}, split={self.split.name!r}, "
            f"frames={len(self._frames)}, cameras={self._cameras})"
        )
