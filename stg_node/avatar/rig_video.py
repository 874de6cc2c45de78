"""``stg-train --format video --calibration rig.json``: a rig's videos become a dataset of every camera.

:func:`prepare_rig_videos` finds one recording per camera of the rig (``--data`` a folder holding
``NAME.mp4`` (any video) or ``NAME/`` (images) for each camera NAME of rig.json, or the files
comma-separated in the rig's camera order), tracks them together (stg-track's multi-view
tracker, cached by content: stg_node/tracking/rig_pipeline.py) and writes the confident instants
in the folder format with every camera's calibration (``R``, ``t`` in the rig's world frame),
which the ``video`` format opens. Training then uses every camera unless ``--train-cameras``
picks some (the others are the novel views).
"""

from __future__ import annotations

from pathlib import Path

from stg_node.data.io import IMAGE_SUFFIXES

VIDEO_SUFFIXES = (".mp4", ".mkv", ".avi", ".mov", ".webm", ".m4v")


def rig_inputs(data: str, names: list[str]) -> list[Path]:
    """One recording per camera: ``data`` comma-separated in camera order, or a folder with NAME.* / NAME/."""
    if "," in data:
        paths = [Path(p.strip()) for p in data.split(",") if p.strip()]
        if len(paths) != len(names):
            raise ValueError(
                f"--data names {len(paths)} recordings for the rig's {len(names)} cameras "
                f"({', '.join(names)})"
            )
        missing = [str(p) for p in paths if not p.exists()]
        if missing:
            raise FileNotFoundError(f"--data: no such recording: {', '.join(missing)}")
        return paths
    folder = Path(data)
    if not folder.is_dir():
        raise FileNotFoundError(
            f"--data {data}: with --calibration, a folder holding one recording per camera (NAME.mp4 or "
            "NAME/), or the recordings comma-separated in the rig's camera order"
        )
    found, missing = [], []
    for name in names:
        candidates = [p for p in folder.glob(f"{name}.*") if p.suffix.lower() in VIDEO_SUFFIXES]
        images = folder / name
        if images.is_dir() and any(p.suffix.lower() in IMAGE_SUFFIXES for p in images.iterdir()):
            candidates.append(images)
        if len(candidates) != 1:
            missing.append(f"{name} ({'none' if not candidates else ', '.join(p.name for p in candidates)})")
        else:
            found.append(candidates[0])
    if missing:
        raise FileNotFoundError(
            f"--data {folder}: needs exactly one recording (NAME{'|'.join(VIDEO_SUFFIXES)} or an image "
            f"folder NAME/) per rig camera; unclear for: {'; '.join(missing)}"
        )
    return found


def prepare_rig_videos(
    data: str,
    out: Path,
    calibration: str | Path,
    *,
    smpl_model: str | None = None,
    progress: bool = True,
    threads: int | None = None,
) -> Path:
    """Track the rig's recordings into the folder format under ``out``; returns ``out``."""
    from stg_node.calibration.rig import read_rig
    from stg_node.tracking import TrackOptions
    from stg_node.tracking.rig_pipeline import rig_to_folder

    rig = read_rig(calibration)
    inputs = rig_inputs(data, rig.names)
    return rig_to_folder(
        inputs, calibration, out, TrackOptions(smpl_model=smpl_model), progress=progress, threads=threads
    )
