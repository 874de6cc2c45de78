"""Open a generated benchmark with the ZJU-MoCap loader, using the frame rate and splits in synth.json.

``stg-synth`` writes ZJU-MoCap's original layout, so :func:`stg_node.data.open_dataset` reads it
like any ZJU subject; what the layout cannot say (the frame rate, and where the training
frames end) comes from ``synth.json``. :func:`open_synth` passes both on, so its ``train``,
``novel_view`` and ``novel_pose`` splits are exactly the views the generator rendered for them.
"""

from __future__ import annotations

from pathlib import Path

from stg_node.data.base import SequenceDataset
from stg_node.data.splits import FrameRange, SplitSpec
from stg_node.data.synth.writer import read_metadata


def loader_name(camera_name: str) -> str:
    """The loader's name of a generated camera: ``Camera_B7`` -> ``"7"``."""
    return camera_name.removeprefix("Camera_B")


def train_cameras(metadata: dict) -> tuple[str, ...]:
    """Loader names of the cameras the generator rendered on every frame (role "train"):
    ``("1",)`` unless it was run with ``--train-cameras``."""
    names = tuple(loader_name(c["name"]) for c in metadata["cameras"] if c.get("role") == "train")
    return names or (loader_name(metadata["cameras"][0]["name"]),)


def synth_split(metadata: dict, name: str) -> SplitSpec:
    """The loader selection of split ``name`` ('train', 'novel_view', 'novel_pose') of a generated folder.

    The training cameras (camera "1", or those of ``stg-synth --train-cameras``) over the training
    frames; the held-out cameras every ``view_every``-th training frame; all cameras every
    ``view_every``-th frame after the training range (the ZJU-MoCap protocol of
    stg_node.data.splits, with the generator's stride instead of 30).
    """
    n_train = int(metadata["num_train_frames"])
    every = int(metadata["view_every"])
    train = train_cameras(metadata)
    if name == "train":
        return SplitSpec("train", FrameRange(0, n_train), cameras=train)
    if name == "novel_view":
        return SplitSpec("novel_view", FrameRange(0, n_train, every), exclude=train)
    if name == "novel_pose":
        return SplitSpec("novel_pose", FrameRange(n_train, None, every))
    raise ValueError(f"unknown split {name!r}; use 'train', 'novel_view', 'novel_pose' or a SplitSpec")


def open_synth(path: str | Path, split: str | SplitSpec = "train", **options) -> SequenceDataset:
    """Open one split of an ``stg-synth`` folder (options as :func:`stg_node.data.open_dataset`).

    ``split`` is 'train', 'novel_view', 'novel_pose' (see :func:`synth_split`) or any
    :class:`SplitSpec`; e.g. every held-out frame of the training camera is
    ``SplitSpec("mono_pose", FrameRange(n_train, None), cameras=("1",))``.
    """
    from stg_node.data.factory import open_dataset

    metadata = read_metadata(Path(path))
    options.setdefault("fps", float(metadata["fps"]))
    options.setdefault("train_frames", FrameRange(0, int(metadata["num_train_frames"])))
    if isinstance(split, str):
        split = synth_split(metadata, split)
    return open_dataset(path, kind="zju", split=split, **options)
