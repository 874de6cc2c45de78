"""Which of the surface the training views see (stg_node.data.synth.coverage), on hand-built scenes."""

from __future__ import annotations

import numpy as np
import pytest

from stg_node.data.synth.coverage import coverage, face_areas, seen_faces
from stg_node.data.types import Camera


def _square(x0, x1, y0, y1, z):
    """Two triangles of an axis-aligned rectangle at depth z."""
    return [(x0, y0, z), (x1, y0, z), (x1, y1, z), (x0, y1, z)]


def _scene():
    """A: 0.4 x 0.4 m at z = 2; B: the same size at z = 3, behind A; C: 0.2 x 0.4 m at z = 2 beside A."""
    squares = [
        _square(-0.2, 0.2, -0.2, 0.2, 2.0),
        _square(-0.2, 0.2, -0.2, 0.2, 3.0),
        _square(0.3, 0.5, -0.2, 0.2, 2.0),
    ]
    vertices = np.array([v for sq in squares for v in sq], np.float64)
    faces = np.array(
        [[4 * k, 4 * k + 1, 4 * k + 2] for k in range(3)] + [[4 * k, 4 * k + 2, 4 * k + 3] for k in range(3)]
    )
    return vertices, faces  # faces k and k + 3 are square k's


K = np.array([[100.0, 0.0, 32.0], [0.0, 100.0, 32.0], [0.0, 0.0, 1.0]])
FRONT = Camera(K, np.eye(3), np.zeros(3), 64, 64)  # at the origin, looking along +z
# at z = 5 looking back along -z (rotated 180 degrees about y): t = -R c
BACK = Camera(K, np.diag([-1.0, 1.0, -1.0]), -np.diag([-1.0, 1.0, -1.0]) @ np.array([0.0, 0.0, 5.0]), 64, 64)


def test_a_face_hidden_behind_another_is_not_seen():
    vertices, faces = _scene()
    assert seen_faces(vertices, faces, FRONT).tolist() == [True, False, True, True, False, True]
    # from behind, B is the nearer and hides A (A projects smaller than B there); C is beside both
    assert seen_faces(vertices, faces, BACK, supersample=2).tolist() == [False, True, True, False, True, True]


def test_areas_and_shares_over_views():
    """From the front only, B (0.16 of 0.40 m^2) is never seen: 40 %. Front and back: every face is
    seen, A and B once each (80 % of the area in at most one view), C in both."""
    vertices, faces = _scene()
    assert face_areas(vertices, faces).sum() == pytest.approx(0.16 + 0.16 + 0.08)
    front = coverage([(vertices, FRONT), (vertices, FRONT)], faces, vertices)
    assert front.views == 2 and front.views_seen.tolist() == [2, 0, 2, 2, 0, 2]
    assert front.fraction_never_seen() == pytest.approx(0.4)
    both = coverage([(vertices, FRONT), (vertices, BACK)], faces, vertices)
    assert both.fraction_never_seen() == 0.0
    assert both.fraction_seen_in_at_most(1) == pytest.approx(0.8)
    assert both.fraction_seen_in_at_least(1.0) == pytest.approx(0.2)
