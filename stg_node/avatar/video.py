"""``stg-train --format video``: a bare video becomes a dataset through the tracker (stg-track).

:func:`prepare_video` runs :func:`stg_node.tracking.video_to_folder`: the video (or image folder)
is tracked once (SMPL pose and shape per frame, a person mask, a confidence; cached by the
video's content and the options under ``$STG_TRACK_CACHE``), and its confident frames are
written under ``out`` in the folder format (docs/DATASETS.md), which the data spec's ``video``
format opens. The camera is the tracking's: ``--intrinsics FILE.json`` (``K``, optional
``dist``), a pinhole with ``--fov`` degrees of horizontal field of view, or, with neither, the
focal length the tracker estimates from the footage (stg_node.tracking.focal); the world frame
is the camera's (``R = I``, ``t = 0``). Before training, ``RUN_DIR/fit_preview.mp4`` shows the
fit (mesh and mask over every frame, its confidence, the frames skipped and why:
stg_node.tracking.preview), and ``RUN_DIR/video_data/tracking.json`` counts them.
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
    preview: Path | None = None,
) -> Path:
    """Track ``source`` (a video file or image folder) into the folder format under ``out``; returns ``out``.

    ``smpl_model`` is the body the fit uses (the one training must use too; None: the open body).
    Frames tracked with confidence below 0.5 are left out. ``preview``: where to write the fit
    preview (an .mp4), from the cached tracking. Raises ValueError (nothing confident
    enough, a bad calibration file), FileNotFoundError (no such input) or
    :class:`~stg_node.tracking.model_files.PoseModelError` (pose networks not installed).
    """
    from stg_node.tracking import TrackOptions, video_to_folder
    from stg_node.tracking.pipeline import track_video
    from stg_node.tracking.preview import write_preview

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
    # No One-Euro smoothing: it lags the fit off the person's mask, and training has its own
    # smoothness term for tracked poses (docs/BENCHMARKS.md, "The fit's silhouette term": the
    # unsmoothed fits train 0.6-0.9 dB better on novel views, two seeds).
    options = TrackOptions(smpl_model=smpl_model, smoothing=False, **camera)
    folder = video_to_folder(source, out, options, progress=progress, threads=threads)
    if preview is not None:
        poses = track_video(source, options, progress=progress, threads=threads)  # cached: no tracking
        write_preview(source, poses, preview, masks_dir=poses.parent / "masks", smpl_model=smpl_model,
                      progress=progress)  # fmt: skip
    return folder
