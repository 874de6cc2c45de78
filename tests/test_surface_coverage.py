"""tools/surface_coverage.py's true-motion column against closed forms: a still subject moves 0 px
per frame, a plane translated sideways by d at depth Z moves f d / Z on every pixel it covers."""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))

import surface_coverage  # noqa: E402

from stg_node.data.synth.writer import VERTICES_DIR  # noqa: E402
from stg_node.data.types import Camera  # noqa: E402

F, SIZE, DEPTH = 100.0, 64, 2.0
SQUARE = np.array([[-0.3, -0.3, DEPTH], [0.3, -0.3, DEPTH], [0.3, 0.3, DEPTH], [-0.3, 0.3, DEPTH]])
FACES = np.array([[0, 1, 2], [0, 2, 3]])


def _views(frames: int) -> list[SimpleNamespace]:
    K = np.array([[F, 0.0, SIZE / 2], [0.0, F, SIZE / 2], [0.0, 0.0, 1.0]])
    camera = Camera(K, np.eye(3), np.zeros(3), SIZE, SIZE, "test")
    return [SimpleNamespace(index=i, camera=camera) for i in range(frames)]


def _benchmark(folder: Path, offsets_x: list[float]) -> Path:
    """A benchmark folder whose subject is the square shifted sideways by ``offsets_x[frame]`` metres."""
    (folder / VERTICES_DIR).mkdir(parents=True)
    for frame, dx in enumerate(offsets_x):
        np.save(folder / VERTICES_DIR / f"{frame}.npy", (SQUARE + [dx, 0.0, 0.0]).astype(np.float32))
    return folder


def test_a_still_subject_moves_zero_pixels(tmp_path):
    folder = _benchmark(tmp_path / "still", [0.0, 0.0, 0.0])
    moved = surface_coverage.true_motion(folder, _views(3), FACES, num_frames=3)
    assert moved.size > 3 * (F * 0.6 / DEPTH - 2) ** 2  # every covered pixel of every view counted
    assert (moved == 0).all()


def test_a_rigid_sideways_translation_moves_f_d_over_z_pixels_a_frame(tmp_path):
    step = 0.1  # metres a frame: F * step / DEPTH = 5 px a frame
    folder = _benchmark(tmp_path / "slide", [step * i for i in range(3)])
    moved = surface_coverage.true_motion(folder, _views(3), FACES, num_frames=3)
    np.testing.assert_allclose(moved, F * step / DEPTH, atol=1e-3)


def test_the_last_frame_of_a_clip_takes_its_motion_from_the_frame_before(tmp_path):
    """Frame 0 -> 1 slides 0.1 m, 1 -> 2 is still, 2 -> 3 slides 0.2 m. A cut before frame 2 makes
    frame 1 the end of its clip: it compares with frame 0 (5 px) instead of frame 2 (0 px)."""
    folder = _benchmark(tmp_path / "cut", [0.0, 0.1, 0.1, 0.3])
    for cuts, expected in (((), [5.0, 0.0, 10.0, 10.0]), ((2,), [5.0, 5.0, 10.0, 10.0])):
        for view, px in zip(_views(4), expected, strict=True):
            moved = surface_coverage.true_motion(folder, [view], FACES, num_frames=4, cuts=cuts)
            np.testing.assert_allclose(moved, px, atol=1e-3, err_msg=f"frame {view.index}, cuts {cuts}")
