"""Ground-truth image motion from the benchmark's vertices: closed forms for planes, occlusion,
and agreement with the masks the generator wrote."""

from __future__ import annotations

import numpy as np
import pytest

from stg_node.data.synth.true_flow import benchmark_true_flow, fast_region, true_flow
from stg_node.data.types import Camera

F, SIZE = 100.0, 64
SQUARE_FACES = np.array([[0, 1, 2], [0, 2, 3]])


def _camera() -> Camera:
    K = np.array([[F, 0.0, SIZE / 2], [0.0, F, SIZE / 2], [0.0, 0.0, 1.0]])
    return Camera(K, np.eye(3), np.zeros(3), SIZE, SIZE, "test")


def _square(half: float, depth: float, centre=(0.0, 0.0)) -> np.ndarray:
    cx, cy = centre
    return np.array(
        [
            [cx - half, cy - half, depth],
            [cx + half, cy - half, depth],
            [cx + half, cy + half, depth],
            [cx - half, cy + half, depth],
        ]
    )


def _pixel_grid():
    rows, cols = np.mgrid[0:SIZE, 0:SIZE]
    return cols.astype(np.float64), rows.astype(np.float64)


def test_a_sideways_translation_moves_every_pixel_by_f_d_over_z():
    square = _square(0.3, 2.0)
    moved = square + np.array([0.1, -0.05, 0.0])
    out = true_flow(square, moved, SQUARE_FACES, _camera())
    x, y = _pixel_grid()
    inside = (np.abs(x - SIZE / 2) < F * 0.3 / 2.0 - 0.5) & (np.abs(y - SIZE / 2) < F * 0.3 / 2.0 - 0.5)
    assert out.covered[inside].all()
    assert out.covered.sum() <= (F * 0.6 / 2.0 + 2) ** 2
    np.testing.assert_allclose(
        out.flow[out.covered],
        np.broadcast_to([F * 0.1 / 2.0, -F * 0.05 / 2.0], (out.covered.sum(), 2)),
        atol=1e-4,
    )
    assert (out.flow[~out.covered] == 0).all()


def test_moving_towards_the_camera_expands_about_the_principal_point():
    """A plane at depth Z moved to Z - dz: the point at pixel p goes to c + (p - c) Z / (Z - dz)."""
    z, dz = 2.0, 0.4
    square = _square(0.5, z)
    out = true_flow(square, square - np.array([0.0, 0.0, dz]), SQUARE_FACES, _camera())
    x, y = _pixel_grid()
    expected = np.stack([(x - SIZE / 2) * dz / (z - dz), (y - SIZE / 2) * dz / (z - dz)], axis=-1)
    np.testing.assert_allclose(out.flow[out.covered], expected[out.covered], atol=1e-3)
    region = fast_region(out, threshold_px=4.9)
    radius = np.hypot(x - SIZE / 2, y - SIZE / 2) * dz / (z - dz)
    np.testing.assert_array_equal(region, out.covered & (radius > 4.9))


def test_what_is_hidden_does_not_count():
    """A still square in front of a moving one: where the front one covers, nothing moves."""
    front = _square(0.2, 1.0, centre=(-0.1, 0.0))
    back = _square(0.6, 3.0)
    vertices = np.concatenate([front, back])
    faces = np.concatenate([SQUARE_FACES, SQUARE_FACES + 4])
    moved = vertices.copy()
    moved[4:] += np.array([0.3, 0.0, 0.0])
    out = true_flow(vertices, moved, faces, _camera())
    x, y = _pixel_grid()
    in_front = (np.abs(x - (SIZE / 2 - F * 0.1)) < F * 0.2 - 0.5) & (np.abs(y - SIZE / 2) < F * 0.2 - 0.5)
    assert in_front.sum() > 100
    assert (out.magnitude[in_front] == 0).all()
    visible_back = out.covered & ~in_front & (out.magnitude > 0)
    np.testing.assert_allclose(out.magnitude[visible_back], F * 0.3 / 3.0, atol=1e-4)
    assert visible_back.sum() > 300


def test_bad_input_is_a_clear_error():
    square = _square(0.3, 2.0)
    with pytest.raises(ValueError, match=r"\(V, 3\)"):
        true_flow(square, square[:3], SQUARE_FACES, _camera())
    with pytest.raises(ValueError, match="faces index vertex 3"):
        true_flow(square[:3], square[:3], SQUARE_FACES, _camera())
    with pytest.raises(ValueError, match="threshold_px"):
        fast_region(true_flow(square, square, SQUARE_FACES, _camera()), -1.0)


@pytest.fixture(scope="module")
def tiny_dance(tmp_path_factory):
    from stg_node.data.synth.generate import SynthConfig, generate

    out = tmp_path_factory.mktemp("true_flow") / "dance"
    generate(
        SynthConfig(
            out=out, num_frames=4, size=96, motion="dance", num_novel_views=1, view_every=2, supersample=1
        ),
        progress=False,
    )
    return out


def test_the_benchmark_flow_covers_exactly_the_written_masks(tiny_dance):
    """The loader's cameras, the written vertices and this projection agree: the covered pixels are
    the generator's masks (one sample per pixel, so only silhouette ties may differ)."""
    from stg_node.body import load_body_model
    from stg_node.data.synth.dataset import open_synth

    faces = load_body_model().faces.cpu().numpy()
    for split in ("train", "novel_view"):
        for sample in open_synth(tiny_dance, split, size=96):
            out = benchmark_true_flow(tiny_dance, sample.index, sample.camera, faces, num_frames=4)
            mask = sample.mask > 127
            iou = (out.covered & mask).sum() / (out.covered | mask).sum()
            assert iou > 0.99, (split, sample.index, iou)
            assert np.isfinite(out.flow).all() and out.magnitude[out.covered].max() > 0.1
    with pytest.raises(ValueError, match="outside the sequence"):
        benchmark_true_flow(tiny_dance, 4, sample.camera, faces, num_frames=4)
