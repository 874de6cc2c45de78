"""Which data a run trains and is evaluated on: one record, saved in the run, used by every command.

``stg-train`` writes it into ``RUN_DIR/config.json``; ``stg-eval``, ``stg-render`` and
``stg-export`` read it back, so the test splits always follow the training range and camera the
run actually used. Formats:

- ``zju``: ZJU-MoCap (either layout); 3DGS-Avatar's monocular protocol (camera 1, the subject's
  frame range) unless ``train_frames`` / ``train_camera`` say otherwise; novel view = the other
  cameras every 30th training frame; novel pose = every 30th frame after the range.
- ``synthetic``: an ``stg-synth`` folder (ZJU layout plus synth.json); the generator's splits,
  with ``train_frames`` allowed to narrow the training range (held-out views are taken from the
  generator's grid inside it).
- ``thuman``: THuman4.0 (SMPL-X fits; see docs/DATASETS.md).
- ``folder``: the folder format (docs/DATASETS.md), e.g. a capture of your own.
- ``video``: a video file or image folder; the tracker (stg-track) fits SMPL and masks first. With
  a rig's calibration, one video per camera (tracked together: docs/RIGS.md). ``train_frames``
  counts the video's own frames (:func:`video_positions`), skipped ones included; novel pose is
  every tracked frame after the range.

``train_cameras`` (several cameras: ``stg-train --train-cameras A,B,C``) trains on all of them;
the novel-view split is then every other camera (:class:`stg_node.data.splits.RigProtocol`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import asdict, dataclass
from pathlib import Path

from stg_node.data.errors import DatasetError
from stg_node.data.splits import FrameRange, SplitSpec

FORMATS = ("zju", "synthetic", "thuman", "folder", "video")
SPLITS = ("train", "novel_view", "novel_pose")


def parse_frame_range(text: str | None) -> tuple[int, int] | None:
    """'A:B' -> (A, B); None or '' -> None. A ValueError says what was wrong."""
    if not text:
        return None
    parts = text.split(":")
    if len(parts) != 2:
        raise ValueError(f"--train-frames must be A:B (e.g. 0:100), got {text!r}")
    try:
        a, b = int(parts[0] or 0), int(parts[1])
    except ValueError:
        raise ValueError(f"--train-frames must be two integers A:B, got {text!r}") from None
    if a < 0 or b <= a:
        raise ValueError(f"--train-frames needs 0 <= A < B, got {text!r}")
    return a, b


@dataclass(frozen=True)
class DataSpec:
    root: str
    format: str
    train_frames: tuple[int, int] | None = None
    train_camera: str | None = None
    size: int = 512
    train_cameras: tuple[str, ...] | None = None  # several training cameras (a rig); excludes train_camera

    def __post_init__(self):
        if self.format not in FORMATS:
            raise ValueError(f"--format must be one of {', '.join(FORMATS)}, got {self.format!r}")
        if self.train_cameras is not None:
            cameras = tuple(str(c) for c in self.train_cameras)
            if not cameras or len(set(cameras)) != len(cameras):
                raise ValueError(f"--train-cameras must name distinct cameras, got {list(cameras)}")
            if self.train_camera is not None:
                raise ValueError("give --train-camera (one) or --train-cameras (several), not both")
            object.__setattr__(self, "train_cameras", cameras)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["train_frames"] = list(self.train_frames) if self.train_frames else None
        d["train_cameras"] = list(self.train_cameras) if self.train_cameras else None
        return d

    @classmethod
    def from_dict(cls, d: dict) -> DataSpec:
        tf = d.get("train_frames")
        cams = d.get("train_cameras")
        return cls(
            d["root"],
            d["format"],
            tuple(tf) if tf else None,
            d.get("train_camera"),
            int(d.get("size", 512)),
            tuple(cams) if cams else None,
        )

    def with_root(self, root: str | Path) -> DataSpec:
        return dataclasses.replace(self, root=str(root))

    @property
    def rig(self) -> bool:
        """Trains on several cameras."""
        return bool(self.train_cameras) and len(self.train_cameras) > 1

    def open(self, split: str):
        """The SequenceDataset of ``split`` ('train', 'novel_view', 'novel_pose')."""
        if split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
        root = Path(self.root)
        if not root.exists():
            raise DatasetError(root, "does not exist", "the dataset folder given to --data")
        frames = FrameRange(*self.train_frames) if self.train_frames else None
        if self.format == "synthetic":
            return self._open_synth(root, split)
        if frames is not None and self.format == "video":
            frames = video_positions(root, frames)
        from stg_node.data.factory import open_dataset

        kind = {"zju": "zju", "thuman": "thuman4"}.get(self.format, "folder")
        if self.train_cameras:
            return open_dataset(root, kind, self._rig_protocol(root, frames).split(split), size=self.size)
        options = {}
        if frames is not None:
            options["train_frames"] = frames
        if self.train_camera:
            options["train_camera"] = self.train_camera
        if self.format == "zju":
            return open_dataset(root, "zju", split, size=self.size, **options)
        if self.format == "thuman":
            return open_dataset(root, "thuman4", split, size=self.size, **options)
        # folder (docs/DATASETS.md), or video: the tracker turned it into the folder format
        # (see stg_node.avatar.video).
        held_out = frames is not None and frames.stop is not None
        if self.format == "video" and split == "novel_pose" and held_out:
            # Every frame after the training range, not every 30th: a clip's held-out tail is a few
            # hundred frames at most (the walking clip's 99 would give 4), and consecutive frames of
            # one camera are what a viewer of the clip sees.
            split = SplitSpec("novel_pose", FrameRange(frames.stop, None))
        return open_dataset(root, "folder", split, size=self.size, **options)

    def _rig_protocol(self, root: Path, frames: FrameRange | None):
        """The training range of the dataset's own protocol (ZJU-MoCap's per subject, else every
        frame) unless --train-frames gives one, with the rig's cameras."""
        from stg_node.data.splits import RigProtocol, zju_protocol

        if frames is None:
            frames = zju_protocol(root.name).train_frames if self.format == "zju" else FrameRange()
        return RigProtocol(
            self.train_cameras, frames, f"{self.format}: cameras {', '.join(self.train_cameras)}"
        )

    def _open_synth(self, root: Path, split: str):
        from stg_node.data.synth.dataset import loader_name, open_synth, train_cameras
        from stg_node.data.synth.writer import read_metadata

        meta = read_metadata(root)
        n_train, every = int(meta["num_train_frames"]), int(meta["view_every"])
        if self.train_cameras:
            train_cams = self.train_cameras
        elif self.train_camera:
            train_cams = (self.train_camera,)
        else:
            train_cams = train_cameras(meta)
        a, b = self.train_frames or (0, n_train)
        if b > n_train:
            raise DatasetError(
                root,
                f"--train-frames {a}:{b} reaches past the generator's training range (0:{n_train})",
                f"a range inside 0:{n_train}; frames after it are the novel poses",
            )
        rendered = {loader_name(name): set(frames) for name, frames in meta.get("rendered", {}).items()}
        for cam in train_cams:
            if cam in rendered and not set(range(a, b)) <= rendered[cam]:
                dense = sorted((c for c, f in rendered.items() if set(range(a, b)) <= f), key=int)
                raise DatasetError(
                    root,
                    f"camera {cam} was rendered on every {every}th frame only, not on every training frame",
                    f"a camera rendered on frames {a}-{b - 1} ({', '.join(dense)}), or a benchmark generated "
                    f"with stg-synth --train-cameras {','.join(train_cams)}",
                )
        if split == "train":
            spec = SplitSpec("train", FrameRange(a, b), cameras=tuple(train_cams))
        elif split == "novel_view":
            start = math.ceil(a / every) * every
            spec = SplitSpec("novel_view", FrameRange(start, b, every), exclude=tuple(train_cams))
        else:
            spec = SplitSpec("novel_pose", FrameRange(n_train, None, every))
        return open_synth(root, spec, size=self.size)


def video_positions(root: Path, frames: FrameRange) -> FrameRange:
    """A video's ``--train-frames A:B`` (the video's frame numbers, as a player shows them) as
    positions in its tracked folder, which holds only the frames the tracker was sure of (its
    images keep their frame numbers): training takes the kept frames numbered A..B-1 and the
    novel-pose split the kept frames from B on. Counted as positions, a clip with skipped
    frames would train past B on frames the user holds out (the benchmark's tracked dancer, 17 of
    90 frames skipped: ``0:72`` trained up to frame 88 and left one held-out frame)."""
    from bisect import bisect_left

    from stg_node.data.factory import open_dataset

    numbers = sorted(open_dataset(root, "folder", "all", size=None).all_frames)
    start = bisect_left(numbers, frames.start)
    stop = None if frames.stop is None else bisect_left(numbers, frames.stop)
    if stop is not None and stop <= start:
        raise DatasetError(
            root,
            f"has no tracked frame in --train-frames {frames.start}:{frames.stop} (the tracker kept "
            f"{len(numbers)} frames, {numbers[0]}..{numbers[-1]})",
            "a training range with frames the tracker was sure of (RUN_DIR/fit_preview.mp4 shows them)",
        )
    return FrameRange(start, stop, frames.step)
