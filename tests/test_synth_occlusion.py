"""The synthetic benchmark's self-shadowing (stg_node/data/synth/occlusion.py) against closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from stg_node.data.synth.lighting import ROOM_LIGHT_DIRECTION, lighting
from stg_node.data.synth.occlusion import ambient_occlusion, sphere_directions, visibility


def _box(x0, x1, y0, y1, z0, z1):
    """A closed axis-aligned box: 8 vertices, 12 triangles wound outwards."""
    v = [[x, y, z] for x in (x0, x1) for y in (y0, y1) for z in (z0, z1)]
    f = [
        [0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
        [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3],
    ]  # fmt: skip
    return torch.tensor(v, dtype=torch.float64), torch.tensor(f)


def _sphere(radius=1.0, subdivisions=3):
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return torch.tensor(mesh.vertices), torch.tensor(mesh.faces), torch.tensor(mesh.vertex_normals)


def test_directions_cover_the_sphere_evenly():
    dirs = sphere_directions(500)
    assert np.allclose(np.linalg.norm(dirs, axis=1), 1.0)
    assert np.abs(dirs.mean(axis=0)).max() < 0.01  # no side favoured
    # the cosine-weighted mean over a hemisphere is 1/2 of the directions' share (int cos = pi)
    assert (dirs[:, 2] > 0).mean() == pytest.approx(0.5, abs=0.01)


def _polygon_form_factor(point, normal, corners) -> float:
    """Lambert's closed form: the share of a differential area's cosine-weighted hemisphere that a
    planar polygon above its horizon covers, ``(1 / 2 pi) sum_i g_i n . (R_i x R_i+1) / |R_i x R_i+1|``
    with ``R_i`` the vectors to the corners and ``g_i`` the angle between consecutive ones."""
    rays = np.asarray(corners, np.float64) - np.asarray(point, np.float64)
    total = 0.0
    for a, b in zip(rays, np.roll(rays, -1, axis=0), strict=True):
        cross = np.cross(a, b)
        angle = math.atan2(np.linalg.norm(cross), a @ b)
        total += angle * (np.asarray(normal) @ cross) / np.linalg.norm(cross)
    return abs(total) / (2.0 * math.pi)


@pytest.mark.parametrize("distance, height", [(0.5, 1.0), (0.2, 1.0), (1.0, 0.5), (0.3, 3.0)])
def test_floor_point_beside_a_wall_sees_the_closed_form_sky(distance, height):
    """A point on the floor (normal up) at ``distance`` from a wall 3 m long and ``height`` high:
    the wall covers its polygon form factor (Lambert's formula), the rest of the sky is open."""
    corners = [(distance, -1.5, 0.0), (distance, 1.5, 0.0), (distance, 1.5, height), (distance, -1.5, height)]
    wall = torch.tensor(corners, dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    point = torch.zeros(1, 3, dtype=torch.float64)
    up = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    expected = 1.0 - _polygon_form_factor((0, 0, 0), (0, 0, 1), corners)
    got = float(ambient_occlusion(point, up, wall, faces, directions=400, texel_m=0.02)[0])
    assert got == pytest.approx(expected, abs=0.03)


def test_the_polygon_form_factor_of_a_long_wall_is_the_infinite_strips():
    """The closed form of the test above against the one of an infinitely long wall,
    ``(1 - a / sqrt(a^2 + H^2)) / 2``: a 200 m wall is the same to 1e-4."""
    corners = [(0.5, -100, 0), (0.5, 100, 0), (0.5, 100, 1.0), (0.5, -100, 1.0)]
    assert _polygon_form_factor((0, 0, 0), (0, 0, 1), corners) == pytest.approx(
        0.5 * (1 - 0.5 / math.hypot(0.5, 1.0)), abs=1e-4
    )


def test_a_convex_body_does_not_occlude_itself_and_a_cavity_does():
    vertices, faces, normals = _sphere()
    ao = ambient_occlusion(vertices, normals, vertices, faces, directions=64, texel_m=0.02)
    assert float(ao.min()) > 0.97  # a sphere sees the whole sky from every point of its surface
    # the same sphere's surface points seen from inside (normals inward) see only the sphere
    inside = ambient_occlusion(vertices * 0.98, -normals, vertices, faces, directions=64, texel_m=0.02)
    assert float(inside.max()) < 0.03


def test_a_light_is_blocked_by_what_stands_between_and_not_by_the_surface_itself():
    wall, faces = _box(-0.5, 0.5, -0.5, 0.5, 1.0, 1.1)  # a slab 1 m above the floor
    points = torch.tensor([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, 1.1]], dtype=torch.float64)
    up = torch.tensor([[0.0, 0.0, 1.0]] * 3, dtype=torch.float64)
    lit = visibility(points, up, wall, faces, (0.0, 0.0, 1.0), texel_m=0.02)
    # under the slab: shadowed; beside it: lit; on its top face: lit (no self-shadow acne)
    assert lit.tolist() == [False, True, True]
    # a light below the horizon never lights a point
    assert not bool(visibility(points, up, wall, faces, (0.0, 0.0, -1.0), texel_m=0.02).any())


def test_self_shadow_only_darkens_and_changes_nothing_when_off():
    vertices, faces, _ = _sphere()
    toward = 2.5 * np.asarray(ROOM_LIGHT_DIRECTION)  # a block between the sphere and the room's light
    far, far_faces = _box(*(toward[i // 2] + (-0.6, 0.6)[i % 2] for i in range(6)))
    verts = torch.cat([vertices, far]).float()
    all_faces = torch.cat([faces, far_faces + vertices.shape[0]])
    light = lighting("room")
    plain = light.vertex_shade(verts, all_faces, np.zeros(3))
    shadowed = light.vertex_shade(verts, all_faces, np.zeros(3), self_shadow=True)
    assert bool((shadowed <= plain + 1e-6).all())
    assert float((plain - shadowed).max()) > 0.5  # the block shades the sphere's lit side
    assert torch.equal(light.vertex_shade(verts, all_faces, np.zeros(3), self_shadow=False), plain)
