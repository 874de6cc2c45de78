"""``open_dataset``: one call that recognises a dataset folder's layout and opens a split of it."""

from __future__ import annotations

from pathlib import Path

from stg_node.data.base import SequenceDataset
from stg_node.data.errors import DatasetError
from stg_node.data.splits import SplitSpec

KINDS = ("auto", "zju", "thuman4", "folder")

# What each layout must have at its top level (the first entries decide; see docs/DATASETS.md).
LAYOUT_MARKERS = {
    "zju (original)": ("annots.npy", "new_params/ or params/", "Camera_B*/ or 'Camera (*)'/"),
    "zju (refined)": ("annots.npy", "images/", "mask/", "smpl_params/"),
    "thuman4": ("calibration.json", "images/", "masks/", "smpl_params.npz"),
    "folder": ("cameras.json", "images/", "masks/", "poses.npz"),
}


def detect_layout(path: str | Path) -> str:
    """'zju', 'thuman4' or 'folder' from the files present; a DatasetError listing the layouts otherwise."""
    root = Path(path)
    if not root.is_dir():
        raise DatasetError(root, "is not a folder", "a dataset folder")
    has = {p.name for p in root.iterdir()}
    if "annots.npy" in has and ({"new_params", "params", "smpl_params"} & has):
        return "zju"
    if "calibration.json" in has and "smpl_params.npz" in has:
        return "thuman4"
    if "cameras.json" in has and "poses.npz" in has:
        return "folder"
    listing = sorted(has)[:12]
    expected = "; ".join(f"{name}: {', '.join(files)}" for name, files in LAYOUT_MARKERS.items())
    raise DatasetError(root, f"matches no known layout (it holds {listing})", expected)


def open_dataset(
    path: str | Path,
    kind: str = "auto",
    split: str | SplitSpec = "train",
    *,
    size: int | tuple[int, int] | None = 512,
    check: bool = False,
    **options,
) -> SequenceDataset:
    """Open one split of a dataset folder.

    ``kind``: 'auto' (detect), 'zju' (original or refined ZJU-MoCap, also stg-synth output),
    'thuman4' or 'folder'. ``split``: 'train', 'novel_view', 'novel_pose', 'all' or a
    :class:`SplitSpec`. ``size``: delivered image size (int: square; (w, h); None: native).
    ``check``: verify at open that every view of the split has its files. Further keyword
    options go to the loader (``train_camera``, ``fps``, ``mask_source`` for ZJU ...).
    """
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    if kind == "auto":
        kind = detect_layout(path)
    if kind == "zju":
        from stg_node.data.zju_mocap import ZJUMoCapDataset as cls
    elif kind == "thuman4":
        from stg_node.data.thuman4 import THuman4Dataset as cls
    else:
        from stg_node.data.folder import FolderDataset as cls
    dataset = cls(path, split, size=size, **options)
    if check:
        dataset.check()
    return dataset
