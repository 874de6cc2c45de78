"""Rendering sequences of a trained avatar: orbits, follow cameras, dataset cameras, animations.

The library half of ``stg-render``: choose the poses (a pose file, or the training frames), the
cameras (a turntable orbit around the avatar, a camera that follows the body, or the dataset's
cameras tiled in a grid), render every frame with the novel-pose time rule kept stable along
the sequence, and write an MP4 or PNGs. Orbit and follow cameras frame the avatar
(stg_node.avatar.framing): centred and about two thirds of the image tall whatever the
distance of the training camera, aimed at the body of each frame so a walking subject stays
whole. Every render reports how the avatar sat in its frames (:class:`FramingReport`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stg_node.avatar.cameras import body_front, mean_up
from stg_node.avatar.framing import (
    FramingMeter,
    FramingReport,
    FramingRule,
    follow_cameras,
    orbit_rotations,
    portrait_intrinsics,
    view_rotation,
    viewing_direction,
)
from stg_node.avatar.loading import corrected, load_run_renderer
from stg_node.progress import progress

log = logging.getLogger(__name__)
ORBIT_FRAMES = 120
VIEWS = ("orbit", "follow", "dataset")
FOLLOW_SMOOTH_S = 0.5  # the aim point follows the body averaged over this long


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


@dataclass
class RenderSummary:
    """What :func:`render_run` wrote and how its frames showed the avatar."""

    frames: int
    views: str
    framing: FramingReport


def render_run(
    run_path: Path,
    out: Path,
    *,
    views: str | None = None,
    poses=None,
    frames: int | None = None,
    size: int | None = None,
    fps: float = 30.0,
    data=None,
    device="cpu",
    backend="auto",
    show_progress: bool = True,
    rule: FramingRule | None = None,
    light=None,
) -> RenderSummary:
    """Render a run (see module docstring).

    ``views``: ``orbit`` (a turntable around the avatar), ``follow`` (the training camera's bearing,
    or the body's front when animating, following the body) or ``dataset`` (the dataset's own
    cameras, tiled); None: ``follow`` with ``poses``, else ``orbit``. Orbit and follow cameras
    frame the avatar by ``rule`` (stg_node.avatar.framing: centred, 2/3 of the height).
    ``light``: a shading.LightSpec (None: the model's learned light)."""
    if views is None:
        views = "follow" if poses is not None else "orbit"
    if views not in VIEWS:
        raise ValueError(f"views must be one of {', '.join(VIEWS)}, got {views!r}")
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

    def pose_of(i: int) -> int:
        if poses is not None or views != "orbit":
            return i % len(smpls)
        return min(i * len(smpls) // count, len(smpls) - 1)

    if views == "dataset":
        cams = _dataset_cameras(spec, size)
    else:
        cams = _framed_cameras(
            renderer,
            smpls,
            times,
            [pose_of(i) for i in range(count)],
            reference,
            views,
            size,
            rule,
            animating=poses is not None,
            fps=fps,
            show_progress=show_progress,
        )
    meter = FramingMeter()
    writer = FrameWriter(out, fps)
    try:
        for i in progress(range(count), desc="rendering", unit="frame", enabled=show_progress):
            k = pose_of(i)
            smpl, t = smpls[k], times[k]
            if views == "dataset":
                out_img = tile([renderer.render(c, smpl, t, follow=True).image for c in cams])
            else:
                rendered = renderer.render(cams[i], smpl, t, follow=True)
                meter.add(rendered.alpha)
                out_img = rendered.image
            writer.write(out_img)
    finally:
        writer.close()
    return RenderSummary(writer.count, views, meter.report())


def _framed_cameras(
    renderer, smpls, times, pose_indices, reference, views, size, rule, *, animating, fps, show_progress
):
    """One framed camera per output frame (orbit or follow), aimed at the body of that frame."""
    width = size or reference.width
    height = size or reference.height
    K = portrait_intrinsics(reference.K, reference.height, width, height)
    used = sorted(set(pose_indices))
    up = mean_up([smpls[k].Rh for k in used])
    points = {}
    for k in progress(used, desc="framing", unit="pose", enabled=show_progress):
        points[k] = renderer.posed_points(smpls[k], times[k])
    first = points[pose_indices[0]]
    if animating:  # the body's front, a little from above: nothing says where a camera was
        front = body_front(smpls[pose_indices[0]].Rh)
        eye = first.mean(axis=0) + front - 0.1 * up
    else:  # the training camera's bearing on the body
        eye = -np.asarray(reference.R, np.float64).T @ np.asarray(reference.t, np.float64).reshape(3)
    forward = viewing_direction(eye, first.mean(axis=0), up)
    count = len(pose_indices)
    if views == "orbit":
        rotations = orbit_rotations(forward, up, count)
    else:
        rotations = [view_rotation(forward, up)] * count
    return follow_cameras(
        [points[k] for k in pose_indices],
        rotations,
        K,
        width,
        height,
        rule,
        smooth_frames=max(1, round(FOLLOW_SMOOTH_S * fps)),
        name=views,
    )


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
