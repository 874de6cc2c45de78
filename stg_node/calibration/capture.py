"""A rig's calibration recording -> board detections per synchronised instant -> a calibrated rig.

The recording is one video (or image folder) per camera, all filmed at once while someone
moves the board around (docs/RIGS.md says how). Frames are matched by time stamp
(tracking/sync.py: unsynchronised inputs are an error saying by how much they drift); the board
is looked for in every ``every``-th matched instant of every camera.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from stg_node.calibration.board import BoardDetection, BoardDetector, BoardSpec
from stg_node.calibration.solve import CalibrationResult, calibrate_rig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RigCapture:
    """What the cameras saw: per instant and camera, the board's corners (or None)."""

    names: tuple[str, ...]
    image_sizes: tuple[tuple[int, int], ...]  # (width, height) per camera
    detections: list[list[BoardDetection | None]]  # [instant][camera]
    times: list[float]  # seconds per instant

    def sightings(self) -> dict[str, int]:
        return {n: sum(row[v] is not None for row in self.detections) for v, n in enumerate(self.names)}


def detect_capture(
    inputs: Sequence[str | Path],
    names: Sequence[str],
    spec: BoardSpec,
    *,
    every: int = 1,
    max_skew_s: float | None = None,
    fps: float | None = None,
    progress: bool = True,
) -> RigCapture:
    """Find the board in every ``every``-th synchronised instant of the cameras' recordings."""
    from stg_node.progress import progress as progress_bar
    from stg_node.tracking.sync import match_sources, open_sources, synced_frames

    if len(inputs) != len(names):
        raise ValueError(f"{len(inputs)} inputs for {len(names)} camera names")
    sources = open_sources(inputs, fps)
    match = match_sources(sources, names, max_skew_s)
    detector = BoardDetector(spec)
    detections, times = [], []
    total = (len(match) + every - 1) // every
    bar = progress_bar(total=total, unit="instant", desc="stg-calibrate", enabled=progress)
    try:
        for frame_set in synced_frames(sources, match, every):
            detections.append([detector(frame.image) for frame in frame_set.frames])
            times.append(frame_set.time)
            bar.update(1)
            bar.set_postfix(seen=sum(d is not None for d in detections[-1]), refresh=False)
    finally:
        bar.close()
    sizes = tuple((int(s.width), int(s.height)) for s in sources)
    capture = RigCapture(tuple(names), sizes, detections, times)
    log.info("board seen at %s instants (of %d) per camera", capture.sightings(), len(detections))
    return capture


def calibrate_capture(capture: RigCapture, spec: BoardSpec, **options) -> CalibrationResult:
    """:func:`stg_node.calibration.solve.calibrate_rig` on a capture (options passed on)."""
    return calibrate_rig(list(capture.names), list(capture.image_sizes), capture.detections, spec, **options)
