"""Rendering sequences of a trained avatar: orbits, dataset cameras, animations from pose files.

The library half of ``stg-render``: choose the poses (a pose file, or the training frames), the
cameras (an orbit about the subject, or the dataset's cameras tiled in a grid), render every
frame with the novel-pose time rule kept stable along the sequence, and write an MP4 or PNGs.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from stg_node.avatar.cameras import body_up, orbit
from stg_node.avatar.loading import corrected, load_run_renderer
from stg_node.progress import progress

log = logging.getLogger(__name__)
ORBIT_FRAMES = 120


class FrameWriter:
    """Frames to an MP4 (OpenCV, mp4v) or to numbered PNGs in a folder."""

    def __init__(self, out: Path, fps: float = 30.0):
        self.out = Path(out)
        self.fps = fps
        self.count = 0
        self._video = None
        if self.out.suffix.lower() == ".mp4":
            self.out.parent.mkdir(parents=True, exist_ok=True)
        else:
            self.out.mkdir(parents=True, exist_ok=True)

    def write(self, rgb: np.ndarray) -> None:
        import cv2

        if self.out.suffix.lower() == ".mp4":
            if self._video is None:
                h, w = rgb.shape[:2]
                self._video = cv2.VideoWriter(
                    str(self.out), cv2.VideoWriter_fourcc(*"mp4v"), self.fps, (w, h)
                )
                if not self._video.isOpened():
                    raise OSError(f"cannot open {self.out} for writing an MP4 (OpenCV VideoWriter)")
            self._video.write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        else:
            cv2.imwrite(str(self.out / f"{self.count:06d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        self.count += 1

    def close(self) -> None:
        if self._video is not None:
            self._video.release()
            self._video = None


def load_pose_file(path: str | Path):
    """An SmplSequence from a .npz / .npy file, a folder of per-frame .npy files, or a subject
    folder holding new_params/."""
    from stg_node.body.motion import load_smpl_params

    path = Path(path)
    for sub in ("new_params", "params", "smpl_params"):
        if path.is_dir() and (path / sub).is_dir():
            path = path / sub
            break
    return load_smpl_params(path)


def tile(images: list[np.ndarray]) -> np.ndarray:
    """Images of one size in a near-square grid."""
    n = len(images)
    cols = math.ceil(math.sqrt(n))
    rows = math.ceil(n / cols)
    h, w = images[0].shape[:2]
    grid = np.zeros((rows * h, cols * w, 3), np.uint8)
    for i, im in enumerate(images):
        r, c = divmod(i, cols)
        grid[r * h : (r + 1) * h, c * w : (c + 1) * w] = im
    return grid


def render_run(
    run_path: Path,
    out: Path,
    *,
    views: str = "orbit",
    poses=None,
    frames: int | None = None,
    size: int | None = None,
    fps: float = 30.0,
    data=None,
    device="cpu",
    backend="auto",
    show_progress: bool = True,
    light=None,
) -> int:
    """Render a run (see module docstring); returns the number of frames written. ``light``: a
    shading.LightSpec (None: the model's learned light)."""
    run, renderer, corrections, _ = load_run_renderer(run_path, device=device, backend=backend, light=light)
    spec = run.data_spec()
    if data:
        spec = spec.with_root(Path(data).resolve())
    train = spec.open("train")
    reference = train.camera(train.camera_names[0])
    if poses is not None:
        sequence = load_pose_file(poses)
        smpls = [sequence[i] for i in range(len(sequence))]
        times = [None] * len(smpls)
    else:
        smpls = [corrected(train.smpl(f), corrections.get(f)) for f in train.frames]
        times = [train.time(f) for f in train.frames]
    count = frames or (max(len(smpls), ORBIT_FRAMES) if views == "orbit" and poses is None else len(smpls))
    if views == "orbit":
        first = smpls[0]
        center = _subject_center(renderer, first, reference)
        cams = orbit(center, body_up(first.Rh), reference, count, width=size, height=size)
    else:
        cams = _dataset_cameras(spec, size)
    writer = FrameWriter(out, fps)
    try:
        for i in progress(range(count), desc="rendering", unit="frame", enabled=show_progress):
            k = (
                i % len(smpls)
                if poses is not None or views != "orbit"
                else min(i * len(smpls) // count, len(smpls) - 1)
            )
            smpl, t = smpls[k], times[k]
            if views == "orbit":
                out_img = renderer.render(cams[i], smpl, t, follow=True).image
            else:
                out_img = tile([renderer.render(c, smpl, t, follow=True).image for c in cams])
            writer.write(out_img)
    finally:
        writer.close()
    return writer.count


def _subject_center(renderer, smpl, camera) -> np.ndarray:
    import torch

    from stg_node.avatar.model import BodyState, Camera3

    cam = Camera3.from_camera(camera, device=renderer.device)
    with torch.no_grad():
        posed = renderer.model.pose(BodyState.from_smpl(smpl, renderer.device), 0.0, cam.center)
    return posed.means.mean(0).cpu().numpy().astype(np.float64)


def _dataset_cameras(spec, size):
    """The training camera(s), then the held-out ones (a rig that trains on all has none), at ``size``."""
    import dataclasses

    from stg_node.data.errors import DatasetError

    sized = dataclasses.replace(spec, size=size or spec.size)
    train = sized.open("train")
    cameras = [train.camera(name) for name in train.camera_names]
    try:
        held_out = sized.open("novel_view")
    except DatasetError:
        if not sized.rig:
            raise
        return cameras
    return cameras + [held_out.camera(n) for n in held_out.camera_names]
