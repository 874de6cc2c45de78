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
- ``video``: a video file or image folder; the tracker (stg-track) fits SMPL and masks first.
"""

from __future__ import annotations

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

    def __post_init__(self):
        if self.format not in FORMATS:
            raise ValueError(f"--format must be one of {', '.join(FORMATS)}, got {self.format!r}")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["train_frames"] = list(self.train_frames) if self.train_frames else None
        return d

    @classmethod
    def from_dict(cls, d: dict) -> DataSpec:
        tf = d.get("train_frames")
        return cls(
            d["root"], d["format"], tuple(tf) if tf else None, d.get("train_camera"), int(d.get("size", 512))
        )

    def with_root(self, root: str | Path) -> DataSpec:
        return DataSpec(str(root), self.format, self.train_frames, self.train_camera, self.size)

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
        from stg_node.data.factory import open_dataset

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
        return open_dataset(root, "folder", split, size=self.size, **options)

    def _open_synth(self, root: Path, split: str):
        from stg_node.data.synth.dataset import open_synth
        from stg_node.data.synth.writer import read_metadata

        meta = read_metadata(root)
        n_train, every = int(meta["num_train_frames"]), int(meta["view_every"])
        train_cam = self.train_camera or meta["cameras"][0]["name"].removeprefix("Camera_B")
        a, b = self.train_frames or (0, n_train)
        if b > n_train:
            raise DatasetError(
                root,
                f"--train-frames {a}:{b} reaches past the generator's training range (0:{n_train})",
                f"a range inside 0:{n_train}; frames after it are the novel poses",
            )
        if split == "train":
            spec = SplitSpec("train", FrameRange(a, b), cameras=(train_cam,))
        elif split == "novel_view":
            start = math.ceil(a / every) * every
            spec = SplitSpec("novel_view", FrameRange(start, b, every), exclude=(train_cam,))
        else:
            spec = SplitSpec("novel_pose", FrameRange(n_train, None, every))
        return open_synth(root, spec, size=self.size)
