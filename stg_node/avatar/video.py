"""``stg-train --format video``: a bare video becomes a dataset through the tracker (stg-track)."""

from __future__ import annotations

from pathlib import Path


def prepare_video(source: str | Path, out: Path, *, smpl_model=None) -> Path:
    """Track ``source`` (a video file or image folder) into the folder format under ``out``."""
    raise ValueError(
        "--format video needs the live tracker (stg-track), which this build does not have yet; "
        "track the video with your own SMPL fitter and use --format zju or the folder layout "
        "(docs/DATASETS.md)"
    )
