"""Where the benchmark's garment is: closed-form masks for planes (occlusion included), and the
looseness recomputed from synth.json against the garment offsets the generator wrote."""

from __future__ import annotations

import numpy as np
import pytest

from stg_node.data.synth.garment_truth import garment_faces, garment_pixels, on_garment
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


def _inside(centre_m, half_m: float, depth: float) -> np.ndarray:
    """Pixel centres strictly inside the square's image: |p - c| < F half / z (edges chosen off-grid)."""
    rows, cols = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
    cx, cy = SIZE / 2 + F * centre_m[0] / depth, SIZE / 2 + F * centre_m[1] / depth
    r = F * half_m / depth
    return (np.abs(cols - cx) < r) & (np.abs(rows - cy) < r)


def test_the_mask_is_the_garment_square_minus_what_hides_it():
    """A garment square, a skin square beside it and a skin square in front of part of it: the mask is
    the garment square's image minus the front square's, exactly (edges fall a quarter pixel off the
    pixel centres, so no sample is on an edge)."""
    garment = _square(0.305, 2.0, centre=(-0.3, 0.0))  # 15.25 px half-width, centre 15 px left
    skin = _square(0.305, 2.0, centre=(0.35, 0.0))
    front = _square(0.0525, 1.0, centre=(-0.2, 0.1))  # 5.25 px half-width, in front of the garment
    vertices = np.concatenate([garment, skin, front])
    faces = np.concatenate([SQUARE_FACES, SQUARE_FACES + 4, SQUARE_FACES + 8])
    is_garment = np.array([True, True, False, False, False, False])
    mask = garment_pixels(vertices, faces, is_garment, _camera())
    expected = _inside((-0.3, 0.0), 0.305, 2.0) & ~_inside((-0.2, 0.1), 0.0525, 1.0)
    assert (
        expected.sum() > 500
        and (_inside((-0.2, 0.1), 0.0525, 1.0) & _inside((-0.3, 0.0), 0.305, 2.0)).sum() > 50
    )
    np.testing.assert_array_equal(mask, expected)
    # Moved behind the skin square (its image within the skin's), the garment is hidden; alone, seen.
    vertices[:4] = _square(0.305, 5.0, centre=(0.875, 0.0))
    assert not garment_pixels(vertices, faces, is_garment, _camera()).any()
    alone = garment_pixels(vertices[:4], SQUARE_FACES, is_garment[:2], _camera())
    np.testing.assert_array_equal(alone, _inside((0.875, 0.0), 0.305, 5.0))


def test_a_face_with_one_loose_vertex_is_garment():
    faces = np.array([[0, 1, 2], [1, 2, 3], [3, 4, 5]])
    assert garment_faces(faces, np.array([0.0, 0.0, 0.3, 0.0, 0.0, 0.0])).tolist() == [True, True, False]
    with pytest.raises(ValueError, match="indices into 3 vertices"):
        garment_faces(faces, np.zeros(3))


def test_on_garment_takes_the_nearest_vertex():
    vertices = np.array([[0.0, 0, 0], [1.0, 0, 0], [0.0, 1, 0]])
    looseness = np.array([0.0, 0.7, 0.0])
    points = np.array([[0.9, 0.1, 0.0], [0.1, 0.8, 0.0], [0.45, 0.0, 0.0], [0.55, 0.0, 0.0]])
    assert on_garment(points, vertices, looseness, chunk=3).tolist() == [True, False, False, True]
    with pytest.raises(ValueError, match="looseness"):
        on_garment(points, vertices, looseness[:2])


@pytest.fixture(scope="module")
def tiny_dance(tmp_path_factory):
    from stg_node.data.synth.generate import SynthConfig, generate

    out = tmp_path_factory.mktemp("garment_truth") / "dance"
    generate(
        SynthConfig(
            out=out, num_frames=6, size=96, motion="dance", num_novel_views=1, view_every=2, supersample=1
        ),
        progress=False,
    )
    return out


def test_the_looseness_from_synth_json_is_where_the_written_surface_leaves_skinning(tiny_dance):
    """Independent truth: the written vertices minus the body posed by the written SMPL parameters are
    the garment's offsets; they are exactly zero where the recomputed looseness is 0, and not zero on
    the loose vertices."""
    import torch

    from stg_node.body import load_body_model
    from stg_node.data.synth.dataset import open_synth
    from stg_node.data.synth.garment_truth import benchmark_garment_pixels, benchmark_looseness
    from stg_node.data.synth.writer import read_frame_vertices

    body = load_body_model()
    looseness = benchmark_looseness(tiny_dance, body)
    loose = looseness > 0
    assert 0.05 < loose.mean() < 0.5
    moved = np.zeros(loose.shape, bool)
    for sample in open_synth(tiny_dance, "train", size=96):
        smpl = sample.smpl
        with torch.no_grad():
            posed = (
                body(
                    betas=torch.as_tensor(np.asarray(smpl.betas, np.float32))[None],
                    poses=torch.as_tensor(np.asarray(smpl.poses, np.float32)).reshape(1, 72),
                    Rh=torch.as_tensor(np.asarray(smpl.Rh, np.float32)).reshape(1, 3),
                    Th=torch.as_tensor(np.asarray(smpl.Th, np.float32)).reshape(1, 3),
                )
                .vertices[0]
                .numpy()
            )
        offset = np.linalg.norm(read_frame_vertices(tiny_dance, sample.index) - posed, axis=1)
        assert offset[~loose].max() < 1e-4, sample.index  # float32 skinning noise only
        moved |= offset > 1e-3
    assert moved[loose].mean() > 0.5 and not moved[~loose].any()
    # The garment pixels of a view lie on the person and are a part of it.
    faces = body.faces.cpu().numpy()
    sample = open_synth(tiny_dance, "novel_view", size=96)[0]
    pixels = benchmark_garment_pixels(
        tiny_dance, sample.index, sample.camera, faces, garment_faces(faces, looseness)
    )
    person = sample.mask > 127
    assert 0.1 < pixels.sum() / person.sum() < 0.7
    assert (pixels & ~person).sum() <= 0.02 * pixels.sum()  # silhouette ties only
