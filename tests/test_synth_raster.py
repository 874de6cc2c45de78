"""The ground-truth mesh rasterizer against closed forms and an independent point-in-polygon test."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from matplotlib.path import Path

from stg_node.data.synth.mesh_raster import (
    TexturedMesh,
    interpolate,
    project_points,
    rasterize,
    render_mesh,
    sample_texture,
    supersampled_intrinsics,
)
from stg_node.data.types import Camera


def _screen(points_xy, depths):
    return torch.tensor(points_xy, dtype=torch.float64), torch.tensor(depths, dtype=torch.float64)


def _cross2(u, v):
    return u[0] * v[1] - u[1] * v[0]


def _pixel_centres(height, width):
    rows, cols = np.mgrid[0:height, 0:width]
    return np.stack([cols.ravel(), rows.ravel()], axis=1).astype(np.float64)


def test_single_triangle_coverage_matches_point_in_polygon_and_area():
    tri = [[3.3, 4.7], [51.2, 9.9], [20.6, 40.1]]
    xy, z = _screen(tri, [2.0, 2.0, 2.0])
    frags = rasterize(xy, z, torch.tensor([[0, 1, 2]]), 48, 64)
    covered = np.zeros(48 * 64, dtype=bool)
    covered[frags.samples.numpy()] = True
    expected = Path(np.array(tri)).contains_points(_pixel_centres(48, 64))
    np.testing.assert_array_equal(covered, expected)
    # The count of covered pixel centres estimates the area to within the perimeter.
    a, b, c = (np.array(p) for p in tri)
    area = 0.5 * abs(_cross2(b - a, c - a))
    perimeter = np.linalg.norm(b - a) + np.linalg.norm(c - b) + np.linalg.norm(a - c)
    assert abs(covered.sum() - area) < perimeter / 2
    np.testing.assert_allclose(frags.depth.numpy(), 2.0, rtol=1e-6)
    np.testing.assert_allclose(frags.bary.sum(1).numpy(), 1.0, atol=1e-6)


def test_tilted_triangle_depth_is_the_ray_plane_intersection():
    K = torch.tensor([[80.0, 0.0, 31.5], [0.0, 80.0, 31.5], [0.0, 0.0, 1.0]], dtype=torch.float64)
    verts = torch.tensor([[-1.0, -0.8, 3.0], [1.2, -0.5, 5.0], [0.1, 1.0, 4.0]], dtype=torch.float64)
    xy, z = project_points(verts, K, torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    frags = rasterize(xy, z, torch.tensor([[0, 1, 2]]), 64, 64)
    assert frags.samples.numel() > 300
    normal = torch.linalg.cross(verts[1] - verts[0], verts[2] - verts[0]).numpy()
    offset = normal @ verts[0].numpy()
    cols = (frags.samples % 64).numpy().astype(np.float64)
    rows = (frags.samples // 64).numpy().astype(np.float64)
    rays = np.linalg.solve(K.numpy(), np.stack([cols, rows, np.ones_like(cols)]))  # z component == 1
    depth = offset / (normal @ rays)
    np.testing.assert_allclose(frags.depth.numpy(), depth, rtol=1e-5)


def test_textured_quad_reproduces_its_texture_under_a_fronto_parallel_camera():
    rng = np.random.default_rng(3)
    texture = rng.integers(0, 256, size=(24, 32, 3), dtype=np.uint8)
    depth, focal = 2.0, 50.0
    # Quad corners on the pixel edges of a 32 x 24 image: texel centres land on pixel centres.
    xs, ys = np.array([-0.5, 31.5]), np.array([-0.5, 23.5])
    K = np.array([[focal, 0, 0], [0, focal, 0], [0, 0, 1.0]])
    corners = np.array([[x, y] for y in ys for x in xs])  # TL, TR, BL, BR in pixels
    verts = np.concatenate([corners * depth / focal, np.full((4, 1), depth)], axis=1)
    uv = np.array([[0.0, 1.0], [1.0, 1.0], [0.0, 0.0], [1.0, 0.0]])  # v grows upwards
    faces = np.array([[0, 2, 1], [1, 2, 3]])
    mesh = TexturedMesh.from_arrays(faces, uv, faces, texture)
    camera = Camera(K=K, R=np.eye(3), t=np.zeros(3), width=32, height=24)
    result = render_mesh(mesh, verts, camera, supersample=1)
    np.testing.assert_array_equal(result.image, texture)
    assert (result.mask == 255).all()
    np.testing.assert_allclose(result.depth, depth, rtol=1e-6)


def test_nearer_triangle_wins_regardless_of_face_order():
    verts = [[5.0, 5.0], [40.0, 8.0], [10.0, 40.0], [20.0, 2.0], [45.0, 30.0], [8.0, 30.0]]
    xy, _ = _screen(verts, [0] * 6)
    depths = torch.tensor([3.0, 3.0, 3.0, 2.0, 2.0, 2.0], dtype=torch.float64)
    for faces in ([[0, 1, 2], [3, 4, 5]], [[3, 4, 5], [0, 1, 2]]):
        frags = rasterize(xy, depths, torch.tensor(faces), 48, 48)
        tri = frags.dense_triangle().numpy().ravel()
        near_face = faces.index([3, 4, 5])
        in_near = Path(np.array(verts[3:])).contains_points(_pixel_centres(48, 48))
        in_far = Path(np.array(verts[:3])).contains_points(_pixel_centres(48, 48))
        assert (in_near & in_far).sum() > 50
        assert (tri[in_near] == near_face).all()
        assert (tri[in_far & ~in_near] == 1 - near_face).all()
        np.testing.assert_allclose(frags.dense_depth().numpy().ravel()[in_near], 2.0, rtol=1e-6)


def test_interpenetrating_triangles_split_along_their_intersection():
    K = torch.tensor([[60.0, 0, 32.0], [0, 60.0, 32.0], [0, 0, 1.0]], dtype=torch.float64)
    # Two big triangles covering the view: one at z = 4 - x (tilted), one at constant z = 4.
    verts = torch.tensor(
        [
            [-3.0, -3.0, 7.0],
            [3.0, -3.0, 1.0],
            [0.0, 3.0, 4.0],
            [-3.0, -3.0, 4.0],
            [3.0, -3.0, 4.0],
            [0.0, 3.0, 4.0],
        ],
        dtype=torch.float64,
    )
    xy, z = project_points(verts, K, torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    frags = rasterize(xy, z, torch.tensor([[0, 1, 2], [3, 4, 5]]), 64, 64)
    cols = (frags.samples % 64).numpy()
    # On the plane z = 4 - x the ray through column u has x = (u - 32) z / 60, so the tilted
    # triangle is nearer exactly where x > 0, i.e. right of the principal point.
    expected = np.where(cols > 32, 0, 1)
    decided = np.abs(cols - 32) > 0
    np.testing.assert_array_equal(frags.triangle.numpy()[decided], expected[decided])


def test_perspective_correct_interpolation_matches_the_analytic_attribute():
    K = torch.tensor([[70.0, 0, 31.5], [0, 70.0, 31.5], [0, 0, 1.0]], dtype=torch.float64)
    # A quad strongly tilted in depth; attribute = the 3D x coordinate (affine on the surface).
    verts = torch.tensor(
        [[-1.0, -1.0, 2.0], [1.0, -1.0, 6.0], [-1.0, 1.0, 2.0], [1.0, 1.0, 6.0]], dtype=torch.float64
    )
    faces = torch.tensor([[0, 2, 1], [1, 2, 3]])
    xy, z = project_points(verts, K, torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    frags = rasterize(xy, z, faces, 64, 64)
    attr = interpolate(frags, faces, verts[:, :1]).numpy()[:, 0]
    cols = (frags.samples % 64).numpy().astype(np.float64)
    rows = (frags.samples // 64).numpy().astype(np.float64)
    ray = np.linalg.solve(K.numpy(), np.stack([cols, rows, np.ones_like(cols)]))
    # Plane z = 4 + 2x: on the ray (x, y, z) = s * ray, s = 4 / (1 - 2 ray_x).
    s = 4.0 / (1.0 - 2.0 * ray[0])
    analytic = s * ray[0]
    np.testing.assert_allclose(attr, analytic, atol=2e-4)
    # Screen-space (affine) interpolation would be far off: the test can tell the difference.
    lam_x = (cols - xy[:, 0].min().item()) / (xy[:, 0].max().item() - xy[:, 0].min().item())
    affine = -1.0 + 2.0 * lam_x
    assert np.abs(affine - analytic).max() > 0.1


def test_supersampled_coverage_integrates_the_area():
    tri = np.array([[2.2, 3.1], [27.7, 6.4], [9.3, 29.8]])
    K = np.array([[10.0, 0, 0], [0, 10.0, 0], [0, 0, 1.0]])
    verts = np.concatenate([tri / 10.0, np.ones((3, 1))], axis=1)
    texture = np.full((2, 2, 3), 200, dtype=np.uint8)
    mesh = TexturedMesh.from_arrays([[0, 1, 2]], np.zeros((3, 2)), [[0, 1, 2]], texture)
    camera = Camera(K=K, R=np.eye(3), t=np.zeros(3), width=32, height=32)
    area = 0.5 * abs(_cross2(tri[1] - tri[0], tri[2] - tri[0]))
    result = render_mesh(mesh, verts, camera, supersample=8)
    assert abs(result.coverage.sum() - area) < 0.01 * area
    # Mask = coverage >= 1/2, image black outside the mask, colour scaled by coverage inside.
    np.testing.assert_array_equal(result.mask == 255, result.coverage >= 0.5)
    assert (result.image[result.mask == 0] == 0).all()
    inside = result.mask == 255
    np.testing.assert_allclose(result.image[inside][:, 0], np.round(200 * result.coverage[inside]), atol=1)


def test_supersampled_intrinsics_place_samples_inside_their_pixel():
    K = np.array([[100.0, 0, 15.5], [0, 100.0, 7.5], [0, 0, 1.0]])
    Ks = supersampled_intrinsics(K, 4).numpy()
    # Pixel (0, 0) spans [-0.5, 0.5]: its first sample centre is at -0.5 + 0.5 / 4 = -0.375.
    # A point projecting to -0.375 in the original image must land on sample 0 of the dense grid.
    x_ray = (-0.375 - K[0, 2]) / K[0, 0]
    assert Ks[0, 0] * x_ray + Ks[0, 2] == pytest.approx(0.0)


def test_backface_culling_drops_triangles_facing_away():
    xy, z = _screen([[5.0, 5.0], [30.0, 5.0], [5.0, 30.0]], [1.0, 1.0, 1.0])
    facing_away = torch.tensor([[0, 1, 2]])  # counter-clockwise on screen (y down) = clockwise seen
    facing_camera = torch.tensor([[0, 2, 1]])
    assert rasterize(xy, z, facing_away, 32, 32, cull_backfaces=True).samples.numel() == 0
    assert rasterize(xy, z, facing_away, 32, 32).samples.numel() > 0
    assert rasterize(xy, z, facing_camera, 32, 32, cull_backfaces=True).samples.numel() > 0


def test_triangles_behind_the_near_plane_are_dropped():
    xy, _ = _screen([[5.0, 5.0], [30.0, 5.0], [5.0, 30.0]], [0, 0, 0])
    z = torch.tensor([1.0, -1.0, 1.0], dtype=torch.float64)
    assert rasterize(xy, z, torch.tensor([[0, 1, 2]]), 32, 32).samples.numel() == 0


def test_bilinear_texture_lookup_closed_form():
    texture = torch.tensor([[[0.0], [10.0]], [[20.0], [30.0]]])  # 2 x 2, row 0 is the top
    # Texel centres: (u, v) = (0.25, 0.75) is the top-left texel, (0.75, 0.25) the bottom-right.
    uv = torch.tensor([[0.25, 0.75], [0.75, 0.25], [0.5, 0.5], [0.0, 1.0], [1.0, 0.0]])
    values = sample_texture(texture, uv)[:, 0].numpy()
    np.testing.assert_allclose(values, [0.0, 30.0, 15.0, 0.0, 30.0], atol=1e-5)


def test_bad_mesh_input_names_the_problem():
    with pytest.raises(ValueError, match="uv_faces"):
        TexturedMesh.from_arrays([[0, 1, 2]], np.zeros((3, 2)), [[0, 1, 5]], np.zeros((2, 2, 3)))
    with pytest.raises(ValueError, match="texture"):
        TexturedMesh.from_arrays([[0, 1, 2]], np.zeros((3, 2)), [[0, 1, 2]], np.zeros((2, 2)))
    mesh = TexturedMesh.from_arrays([[0, 1, 2]], np.zeros((3, 2)), [[0, 1, 2]], np.zeros((2, 2, 3)))
    camera = Camera(K=np.eye(3), R=np.eye(3), t=np.zeros(3), width=4, height=4)
    with pytest.raises(ValueError, match="vertices"):
        render_mesh(mesh, np.zeros((2, 3)), camera)
