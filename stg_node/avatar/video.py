"""``stg-train --format video``: a bare video becomes a dataset through the tracker (stg-track).

:func:`prepare_video` runs :func:`stg_node.tracking.video_to_folder`: the video (or image folder)
is tracked once (SMPL pose and shape per frame, a person mask, a confidence; cached by the
video's content and the options under ``$STG_TRACK_CACHE``), and its confident frames are
written under ``out`` in the folder format (docs/DATASETS.md), which the data spec's ``video``
format opens. The camera is the tracking's: ``--intrinsics FILE.json`` (``K``, optional
``dist``) or a pinhole with ``--fov`` degrees of horizontal field of view; the world frame is
the camera's (``R = I``, ``t = 0``).
"""

from __future__ import annotations

from pathlib import Path


def prepare_video(
    source: str | Path,
    out: Path,
    *,
    smpl_model: str | None = None,
    intrinsics: str | Path | None = None,
    fov_deg: float | None = None,
    progress: bool = True,
    threads: int | None = None,
) -> Path:
    """Track ``source`` (a video file or image folder) into the folder format under ``out``; returns ``out``.

    ``smpl_model`` is the body the fit uses (the one training must use too; None: the open body).
    Frames tracked with confidence below 0.5 are left out. Raises ValueError (nothing confident
    enough, a bad calibration file), FileNotFoundError (no such input) or
    :class:`~stg_node.tracking.model_files.PoseModelError` (pose networks not installed).
    """
    from stg_node.tracking import TrackOptions, video_to_folder

    source = Path(source)
    if not source.exists():
        raise FileNotFoundError(f"--data {source}: no such video file or image folder")
    if intrinsics is not None and fov_deg is not None:
        raise ValueError("give the camera by --intrinsics or by --fov, not both")
    camera = {}
    if intrinsics is not None:
        camera["intrinsics"] = str(intrinsics)
    if fov_deg is not None:
        camera["fov_deg"] = float(fov_deg)
    options = TrackOptions(smpl_model=smpl_model, **camera)
    return video_to_folder(source, out, options, progress=progress, threads=threads)
