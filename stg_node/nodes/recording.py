"""What the renderer writes to disk: numbered PNGs as they are rendered, then an MP4 and a contact sheet.

Images are written as they come (so a killed renderer still leaves them); :meth:`ImageRecorder.finish`
assembles the MP4 (OpenCV, mp4v: the whole session, the avatar learning included) and a contact
sheet: the views the renderer gives it at the end (the trained avatar from the training camera
and around an orbit), or else a grid of evenly spaced recorded frames, labelled.
The number of images kept is bounded (``max_images``): past it every other one is thinned out, so
an endless run does not fill the disk.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

log = logging.getLogger(__name__)


class ImageRecorder:
    def __init__(self, folder: str | Path, *, every: int = 1, max_images: int = 2000, fps: float = 15.0):
        self.folder = Path(folder)
        self.frames_dir = self.folder / "frames"
        self.frames_dir.mkdir(parents=True, exist_ok=True)
        self.every = max(1, every)
        self.max_images = max_images
        self.fps = fps
        self.offered = 0
        self.paths: list[Path] = []
        self.labels: list[str] = []

    def add(self, image_rgb: np.ndarray, label: str = "") -> None:
        self.offered += 1
        if (self.offered - 1) % self.every:
            return
        path = self.frames_dir / f"{self.offered:06d}.png"
        cv2.imwrite(str(path), cv2.cvtColor(image_rgb, cv2.COLOR_RGB2BGR))
        self.paths.append(path)
        self.labels.append(label)
        if len(self.paths) > self.max_images:  # thin out: keep every other image
            for old in self.paths[1::2]:
                old.unlink(missing_ok=True)
            self.paths, self.labels = self.paths[::2], self.labels[::2]
            self.every *= 2

    def finish(
        self, name: str = "avatar", sheet: list[tuple[np.ndarray, str]] | None = None
    ) -> dict[str, str]:
        """Write ``name``.mp4 from the recorded images and ``name``_sheet.png from ``sheet`` ((RGB image,
        label) pairs: what the avatar looks like at the end), else from the recorded images; their paths."""
        written: dict[str, str] = {}
        images = [cv2.imread(str(p)) for p in self.paths]
        images = [im for im in images if im is not None]
        if not images:
            return written
        h, w = images[0].shape[:2]
        video = self.folder / f"{name}.mp4"
        writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), self.fps, (w, h))
        if writer.isOpened():
            for im in images:
                writer.write(im if im.shape[:2] == (h, w) else cv2.resize(im, (w, h)))
            writer.release()
            written["video"] = str(video)
        else:  # pragma: no cover - OpenCV builds without an mp4 writer
            log.warning("OpenCV cannot write %s; the frames stay in %s", video, self.frames_dir)
        sheet_path = self.folder / f"{name}_sheet.png"
        if sheet:
            tiles = [cv2.cvtColor(image, cv2.COLOR_RGB2BGR) for image, _ in sheet]
            grid = contact_sheet(tiles, [label for _, label in sheet], count=len(tiles))
        else:
            grid = contact_sheet(images, self.labels[: len(images)])
        cv2.imwrite(str(sheet_path), grid)
        written["sheet"] = str(sheet_path)
        return written


def contact_sheet(
    images: list[np.ndarray], labels: list[str], *, count: int = 12, columns: int = 4, tile: int = 192
) -> np.ndarray:
    """A grid of ``count`` evenly spaced images (BGR), each ``tile`` pixels on its longer side, labelled."""
    picks = np.unique(np.linspace(0, len(images) - 1, min(count, len(images))).round().astype(int))
    tiles = []
    for i in picks:
        im = images[i]
        scale = tile / max(im.shape[:2])
        im = cv2.resize(
            im,
            (max(1, round(im.shape[1] * scale)), max(1, round(im.shape[0] * scale))),
            interpolation=cv2.INTER_AREA,
        )
        canvas = np.zeros((tile, tile, 3), np.uint8)
        canvas[: im.shape[0], : im.shape[1]] = im
        if i < len(labels) and labels[i]:
            cv2.putText(
                canvas, labels[i], (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA
            )
        tiles.append(canvas)
    rows = []
    for r in range(0, len(tiles), columns):
        row = tiles[r : r + columns]
        row += [np.zeros_like(tiles[0])] * (columns - len(row))
        rows.append(np.concatenate(row, axis=1))
    return np.concatenate(rows, axis=0)
