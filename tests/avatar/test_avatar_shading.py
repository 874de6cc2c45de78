"""Colour that knows where the light is (shading.py), well-shaped Gaussians (the scale-ratio cap) and
the as-isometric-as-possible term (isometry.py), each against an independent truth."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from stg_node.avatar.color import sh_basis
from stg_node.avatar.gaussians import cap_scale_ratio, quaternion_z_to, scale_ratio_percentile
from stg_node.avatar.isometry import IsometryGraph, approximate_knn
from stg_node.avatar.shading import (
    KERNEL,
    LightSpec,
    Shading,
    directional_irradiance,
    gaussian_normals,
    irradiance,
    outward_normals,
    parse_light,
)


def _sphere_directions(n: int) -> np.ndarray:
    """A Fibonacci lattice of ``n`` unit directions (quadrature points of equal area)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + 5**0.5) * i
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _radiance(w: np.ndarray) -> np.ndarray:
    """A known light: L(w) = (1, 0.8, 0.6) + (0.5, 0.3, 0.1) w_z + 0.3 (w_x^2 - w_y^2), per channel."""
    return (
        np.array([1.0, 0.8, 0.6])
        + np.outer(w[:, 2], [0.5, 0.3, 0.1])
        + 0.3 * (w[:, :1] ** 2 - w[:, 1:2] ** 2)
    )


def _closed_form_irradiance(n: np.ndarray) -> np.ndarray:
    """E(n) = int L(w) max(0, n.w) dw of _radiance, band by band (Funk-Hecke): pi for the constant,
    2 pi / 3 for the linear term, pi / 4 for the pure second-order harmonic x^2 - y^2."""
    return (
        math.pi * np.array([1.0, 0.8, 0.6])
        + (2 * math.pi / 3) * np.outer(n[:, 2], [0.5, 0.3, 0.1])
        + (math.pi / 4) * 0.3 * (n[:, :1] ** 2 - n[:, 1:2] ** 2)
    )


def test_sh_irradiance_of_a_known_light_matches_the_closed_form_and_brute_force():
    w = _sphere_directions(40_000)
    dw = 4 * math.pi / w.shape[0]
    radiance = _radiance(w)
    # Project the radiance on the 9 SH functions by quadrature, then convolve with the clamped cosine.
    basis = sh_basis(2, torch.as_tensor(w)).numpy()  # (Q, 9)
    coeffs = (basis.T @ radiance) * dw * np.asarray(KERNEL)[:, None]
    normals = _sphere_directions(300)
    ours = irradiance(torch.as_tensor(normals), torch.as_tensor(coeffs)).numpy()
    np.testing.assert_allclose(ours, _closed_form_irradiance(normals), atol=2e-3)
    brute = np.stack([(radiance * np.clip(w @ n, 0, None)[:, None]).sum(0) * dw for n in normals[:20]])
    np.testing.assert_allclose(ours[:20], brute, atol=5e-3)


def test_directional_lights_convert_to_sh_within_the_second_order_error():
    d = np.array([0.3, -0.5, 0.8])
    d /= np.linalg.norm(d)
    coeffs = directional_irradiance([d], [[0.7, 0.6, 0.5]], ambient=[0.2, 0.25, 0.3])
    normals = _sphere_directions(2000)
    ours = irradiance(torch.as_tensor(normals, dtype=torch.float32), coeffs).numpy()
    exact = np.array([0.2, 0.25, 0.3]) + np.outer(np.clip(normals @ d, 0, None), [0.7, 0.6, 0.5])
    assert np.abs(ours - exact).max() < 0.1 * 0.7  # the clamped cosine's order-2 truncation
    assert np.abs(ours - exact).mean() < 0.03 * 0.7
    # Ambient alone is exact: E = ambient everywhere.
    flat = irradiance(
        torch.as_tensor(normals, dtype=torch.float32), directional_irradiance([], [], [0.4] * 3)
    )
    np.testing.assert_allclose(flat.numpy(), 0.4, atol=1e-6)


def test_a_lambertian_sphere_of_gaussian_discs_renders_the_closed_form_shading():
    """Flat Gaussians tangent to a unit sphere, albedo 0.5, lit by a known SH light and splatted: the
    pixel at the sphere's centre shows albedo x E(n) with n the normal facing the camera."""
    from stg_node.splat import rasterize

    w = _sphere_directions(6000)
    normals_true = torch.as_tensor(w, dtype=torch.float32)
    quats = quaternion_z_to(normals_true)
    scales = torch.tensor([0.05, 0.05, 0.005]).expand(len(w), 3).clone()  # discs: z is the thin axis
    means = normals_true.clone()
    eye = torch.tensor([0.0, -4.0, 0.0])  # the camera looks along +y at the sphere's centre
    normals = gaussian_normals(quats, scales, means, eye)
    facing = (normals_true * (eye - means)).sum(1) > 0
    np.testing.assert_allclose(normals[facing].numpy(), w[facing.numpy()], atol=1e-5)  # outward
    np.testing.assert_allclose(normals[~facing].numpy(), -w[~facing.numpy()], atol=1e-5)  # towards eye
    coeffs = torch.as_tensor(
        (
            sh_basis(2, torch.as_tensor(_sphere_directions(40_000))).numpy().T
            @ _radiance(_sphere_directions(40_000))
        )
        * (4 * math.pi / 40_000)
        * np.asarray(KERNEL)[:, None],
        dtype=torch.float32,
    )
    shading = Shading()
    colors = shading(torch.full((len(w), 3), 0.5), normals, LightSpec.given(coeffs.numpy()))
    view = torch.eye(4)
    view[:3, :3] = torch.tensor([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # x right, z up -> y down
    view[:3, 3] = -view[:3, :3] @ eye
    K = torch.tensor([[200.0, 0, 31.5], [0, 200.0, 31.5], [0, 0, 1.0]])
    image, alpha, _ = rasterize(
        means, quats, scales, torch.full((len(w),), 0.99), colors, view, K, 64, 64, backend="torch"
    )
    centre = image[30:34, 30:34].reshape(-1, 3).mean(0) / alpha[30:34, 30:34].mean()
    expected = 0.5 * _closed_form_irradiance(np.array([[0.0, -1.0, 0.0]]))[0]
    np.testing.assert_allclose(centre.numpy(), expected, rtol=0.02)


def _sphere_of_discs(n: int = 6000):
    w = torch.as_tensor(_sphere_directions(n), dtype=torch.float32)
    scales = torch.tensor([0.05, 0.05, 0.005]).expand(n, 3).clone()  # discs: z is the thin axis
    return w, quaternion_z_to(w), scales


def test_outward_normals_keep_the_disc_side_wherever_the_camera_is():
    """Discs tangent to a sphere, +z out (as the initialisation lays them on the body): outward
    normals are the sphere's outward normals on both sides and stay so when the sphere turns; a
    Gaussian whose shortest axis is not z has no side of its own and faces the camera."""
    w, quats, scales = _sphere_of_discs(500)
    eye = torch.tensor([0.0, -4.0, 0.0])
    np.testing.assert_allclose(outward_normals(quats, scales, w, eye).numpy(), w.numpy(), atol=1e-5)
    np.testing.assert_allclose(
        gaussian_normals(quats, scales, w, eye, outward=True).numpy(), w.numpy(), atol=1e-5
    )
    turn = Rotation.from_euler("z", 150, degrees=True)
    turned_quats = torch.as_tensor(
        (turn * Rotation.from_quat(quats[:, [1, 2, 3, 0]].numpy())).as_quat()[:, [3, 0, 1, 2]],
        dtype=torch.float32,
    )
    turned = w @ torch.as_tensor(turn.as_matrix(), dtype=torch.float32).T
    np.testing.assert_allclose(
        outward_normals(turned_quats, scales, turned, eye).numpy(), turned.numpy(), atol=1e-5
    )
    # Thin along x instead: the disc's side is unknown, so it is flipped towards the camera.
    thin_x = torch.tensor([0.005, 0.05, 0.05]).expand(len(w), 3)
    axes = torch.as_tensor(
        Rotation.from_quat(quats[:, [1, 2, 3, 0]].numpy()).as_matrix()[:, :, 0], dtype=torch.float32
    )
    towards = torch.where(((eye - w) * axes).sum(1, keepdim=True) >= 0, axes, -axes)
    np.testing.assert_allclose(outward_normals(quats, thin_x, w, eye).numpy(), towards.numpy(), atol=1e-5)


def test_discs_seen_from_behind_teach_the_light_nothing():
    """With outward normals a disc seen from behind is shaded by its own side, but its shade passes
    no gradient to the light (or its normal): the light cannot learn to darken what the camera sees
    of backs and silhouettes. The albedo still learns from it."""
    shading = Shading("distant", 2)
    normals = torch.nn.functional.normalize(
        torch.randn(40, 3, generator=torch.Generator().manual_seed(1)), dim=1
    )
    normals.requires_grad_(True)
    away = torch.zeros(40, dtype=torch.bool)
    away[:20] = True
    albedo = torch.rand(40, 3, requires_grad=True)
    colors = shading(albedo, normals, away=away)
    np.testing.assert_allclose(colors.detach().numpy(), shading(albedo, normals).detach().numpy())
    colors[:20].sum().backward()
    assert all(float(p.grad.abs().max()) == 0.0 for p in shading.light.parameters())
    assert float(normals.grad[:20].abs().max()) == 0.0 and float(albedo.grad[:20].abs().min()) > 0.0
    colors = shading(albedo, normals, away=away)
    colors[20:].sum().backward()
    assert all(float(p.grad.abs().max()) > 0.0 for p in shading.light.parameters())


def test_outward_normals_light_the_silhouette_as_the_surface_there():
    """A sphere lit from the side (+x, no ambient), seen along +y: at the right-hand silhouette the
    surface faces the light. Discs just beyond the silhouette still show there; flipped towards the
    camera they face away from the light and darken the rim, outward they stay lit."""
    from stg_node.splat import rasterize

    w, quats, scales = _sphere_of_discs(6000)
    eye = torch.tensor([0.0, -4.0, 0.0])
    light = LightSpec.distant((0.0, 0.0, 0.0), [(1.0, 0.0, 0.0)], [(1.0, 1.0, 1.0)])
    view = torch.eye(4)
    view[:3, :3] = torch.tensor([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    view[:3, 3] = -view[:3, :3] @ eye
    focal = 50.0
    K = torch.tensor([[focal, 0, 31.5], [0, focal, 31.5], [0, 0, 1.0]])
    rims = {}
    for outward in (True, False):
        normals = gaussian_normals(quats, scales, w, eye, outward=outward)
        colors = Shading()(torch.full((len(w), 3), 0.5), normals, light)
        opacities = torch.full((len(w),), 0.99)
        image, alpha, _ = rasterize(w, quats, scales, opacities, colors, view, K, 64, 64, backend="torch")
        # The rim: the right-most covered pixel of each row through the middle, where the surface
        # seen faces +x, across the line of sight.
        values = []
        for row in range(29, 35):
            last = int((alpha[row, :, 0] > 0.5).nonzero().max())
            values.append(float(image[row, last, 0] / alpha[row, last, 0]))
        rims[outward] = float(np.mean(values))
    # Albedo 0.5 x cos(angle between the rim's normal and +x), the angle under 30 degrees.
    assert rims[True] > 0.5 * math.cos(math.radians(30))
    assert rims[False] < rims[True] - 0.03


@pytest.mark.parametrize("light_model", ["distant", "sh"])
def test_baked_light_turns_with_the_body_and_the_learned_one_stays_in_the_world(light_model):
    shading = Shading(light_model)
    with torch.no_grad():  # a light from +x in the room
        if light_model == "sh":
            sh = directional_irradiance([[1.0, 0.0, 0.0]], [[1.0, 1.0, 1.0]], [0.2] * 3)
            shading.light.coefficients.copy_(sh[1:] / (sh[0] * 0.28209479177387814))
        else:
            shading.light.directions[0] = torch.tensor([1.0, 0.0, 0.0])
            shading.light.colors[0] = 3.0
    n = torch.tensor([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    albedo = torch.ones(2, 3)
    turn = torch.as_tensor(Rotation.from_euler("z", 180, degrees=True).as_matrix(), dtype=torch.float32)
    # The body turned half round: its lit side (+x in the room) now faces -x.
    turned_normals = n @ turn.T
    with torch.no_grad():
        learned = shading(albedo, turned_normals)
        baked = shading(albedo, turned_normals, LightSpec("baked"), root_rotation=turn)
        unturned = shading(albedo, n, LightSpec("baked"), root_rotation=torch.eye(3))
    assert learned[1, 0] > learned[0, 0] + 0.5  # the room light now falls on the other side
    np.testing.assert_allclose(baked.numpy(), unturned.numpy(), atol=1e-6)  # baked: it turned along
    np.testing.assert_allclose(shading(albedo, n, LightSpec("albedo")).numpy(), 1.0)
    with pytest.raises(ValueError, match="root orientation"):
        shading(albedo, n, LightSpec("baked"))


def test_the_baked_reference_is_the_mean_training_orientation():
    shading = Shading()
    for angle in (-20.0, 0.0, 20.0):
        shading.add_orientation(torch.as_tensor(Rotation.from_euler("z", angle, degrees=True).as_matrix()))
    np.testing.assert_allclose(shading.reference.numpy(), np.eye(3), atol=1e-6)


def test_uniform_light_leaves_the_colour_unchanged_and_costs_nothing():
    shading = Shading("sh")
    albedo = torch.rand(50, 3)
    normals = torch.nn.functional.normalize(torch.randn(50, 3), dim=1)
    np.testing.assert_allclose(shading(albedo, normals).detach().numpy(), albedo.numpy(), atol=1e-6)
    assert float(shading.penalty().detach()) == 0.0
    # The distant lights start weak: nearly uniform, a small penalty.
    distant = Shading("distant", 2)
    np.testing.assert_allclose(distant(albedo, normals).detach().numpy(), albedo.numpy(), atol=0.05)
    assert float(distant.penalty().detach()) < 1e-3


def test_distant_lights_average_one_and_convert_to_the_same_sh_light():
    """E averages 1 over all directions (the albedo keeps the brightness); its SH form agrees."""
    from stg_node.avatar.shading import DistantLights

    lights = DistantLights(2)
    with torch.no_grad():
        lights.colors.copy_(torch.tensor([[1.0, 0.5, 0.0], [0.2, 0.4, 2.0]]))
        lights.directions.copy_(torch.tensor([[0.3, -0.5, 0.8], [-1.0, 0.2, 0.1]]))
    w = torch.as_tensor(_sphere_directions(40_000), dtype=torch.float32)
    with torch.no_grad():
        e = lights.irradiance(w)
    np.testing.assert_allclose(e.mean(0).numpy(), 1.0, atol=2e-3)
    via_sh = irradiance(w, lights.sh())
    assert float((via_sh - e).abs().mean()) < 0.05  # the second-order truncation of the lobes


def test_light_values_from_the_command_line_and_json_files(tmp_path):
    assert parse_light(None).mode == parse_light("learned").mode == "learned"
    assert parse_light("baked").mode == "baked" and parse_light("albedo").mode == "albedo"
    numbers = ",".join(str(float(i)) for i in range(27))
    np.testing.assert_array_equal(parse_light(numbers).tensor().numpy().reshape(-1), np.arange(27))
    sh_file = tmp_path / "sh.json"
    sh_file.write_text(json.dumps({"sh": [[1.0, 1.0, 1.0]] + [[0.0, 0.0, 0.0]] * 8}))
    assert parse_light(str(sh_file)).tensor()[0, 0] == 1.0
    lights = tmp_path / "lights.json"
    lights.write_text(
        json.dumps({"ambient": [0.3] * 3, "lights": [{"direction": [0, 0, 2], "color": [1, 1, 1]}]})
    )
    spec = parse_light(str(lights))
    np.testing.assert_allclose(
        spec.tensor().numpy(), directional_irradiance([[0, 0, 1]], [[1, 1, 1]], [0.3] * 3).numpy(), atol=1e-6
    )
    normals = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.6, 0.8], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    np.testing.assert_allclose(  # given distant lights are evaluated exactly
        spec.irradiance(normals).numpy(), np.array([[1.3] * 3, [1.1] * 3, [0.3] * 3, [0.3] * 3]), atol=1e-6
    )
    for bad, match in (
        ("1,2,3", "27"),
        ("sunny", "not learned"),
        (str(tmp_path / "missing.json"), "not learned"),
    ):
        with pytest.raises(ValueError, match=match):
            parse_light(bad)
    broken = tmp_path / "broken.json"
    broken.write_text(json.dumps({"lights": [{"direction": [0, 0, 1]}]}))
    with pytest.raises(ValueError, match="direction' and 'color"):
        parse_light(str(broken))


# --- well-shaped Gaussians ------------------------------------------------------------------------
def test_the_scale_ratio_cap_raises_thin_axes_and_keeps_round_ones():
    scales = torch.tensor([[1.0, 0.01, 0.5], [0.2, 0.2, 0.2], [0.3, 0.1, 0.05]], requires_grad=True)
    capped = cap_scale_ratio(scales, 10.0)
    ratio = capped.max(1).values / capped.min(1).values
    assert float(ratio.max().detach()) <= 10.0 + 1e-6
    np.testing.assert_allclose(capped[0].detach().numpy(), [1.0, 0.1, 0.5])  # the needle got thicker
    np.testing.assert_allclose(capped[1:].detach().numpy(), scales[1:].detach().numpy())  # within the cap
    capped[0, 1].backward()  # a raised axis follows the largest one
    np.testing.assert_allclose(scales.grad[0].numpy(), [0.1, 0.0, 0.0])
    assert cap_scale_ratio(scales, 0.0) is scales
    ratios = torch.rand(1000) * 30 + 1
    s = torch.stack([ratios, torch.ones(1000), torch.ones(1000) * 2], dim=1)
    assert scale_ratio_percentile(s) == pytest.approx(float(np.percentile(ratios.numpy(), 99)), rel=1e-6)


def test_disc_initialisation_lies_in_the_surface():
    from stg_node.avatar.config import ModelConfig
    from stg_node.avatar.gaussians import init_table
    from stg_node.body import load_body_model
    from stg_node.body.canonical import big_pose_output

    body = load_body_model()
    vertices = big_pose_output(body, torch.zeros(1, body.num_betas)).vertices[0]
    config = ModelConfig(num_gaussians=500, max_gaussians=1000, init_flatness=0.3)
    table = init_table(config, vertices, body.faces, body.weights, torch.Generator().manual_seed(0))
    scales = table.scales().detach()
    np.testing.assert_allclose((scales[:, 2] / scales[:, 0]).numpy(), 0.3, rtol=1e-5)
    # The thin axis is the normal of the triangle each Gaussian sits on: nearest vertices' normals agree.
    from stg_node.data.synth.mesh_raster import vertex_normals

    vn = vertex_normals(vertices, body.faces)
    nearest = torch.cdist(table["means"], vertices).argmin(1)
    thin = torch.as_tensor(
        Rotation.from_quat(table["quats"].detach().numpy()[:, [1, 2, 3, 0]]).apply([0.0, 0.0, 1.0]),
        dtype=torch.float32,
    )
    agree = (thin * vn[nearest]).sum(1).abs()
    assert float(agree.median()) > 0.95
    sphere = init_table(
        ModelConfig(num_gaussians=50, max_gaussians=100, init_flatness=1.0),
        vertices,
        body.faces,
        body.weights,
        torch.Generator().manual_seed(0),
    )
    np.testing.assert_array_equal(sphere["quats"].detach().numpy()[:, 0], 1.0)  # as before: spheres


def test_quaternion_z_to_turns_z_onto_each_direction_even_straight_down():
    """Against scipy's rotation of z by the quaternion. Float32: random directions come within
    about 1e-5, directions a hair from straight down within about 5e-5 (300 seeds), so the
    tolerance is 1e-4 (a wrong turn is off by order 1); seeded, so a run cannot draw a worse case."""
    d = torch.nn.functional.normalize(torch.randn(100, 3, generator=torch.Generator().manual_seed(0)), dim=1)
    d[0] = torch.tensor([0.0, 0.0, -1.0])
    d[1] = torch.tensor([0.0, 0.0, 1.0])
    d[2] = torch.nn.functional.normalize(torch.tensor([1e-3, 0.0, -1.0]), dim=0)
    d[3] = torch.nn.functional.normalize(torch.tensor([0.0, 1e-5, -1.0]), dim=0)
    q = quaternion_z_to(d).numpy()
    turned = Rotation.from_quat(q[:, [1, 2, 3, 0]]).apply([0.0, 0.0, 1.0])
    np.testing.assert_allclose(turned, d.numpy(), atol=1e-4)


# --- as-isometric-as-possible ---------------------------------------------------------------------
def test_approximate_neighbours_are_near_the_true_ones():
    points = torch.nn.functional.normalize(
        torch.randn(3000, 3, generator=torch.Generator().manual_seed(0)), dim=1
    )
    approx = approximate_knn(points, 8)
    assert not bool((approx == torch.arange(3000)[:, None]).any())  # never itself
    exact = torch.cdist(points, points)
    exact.fill_diagonal_(float("inf"))
    true_knn = exact.topk(8, largest=False)
    found = exact.gather(1, approx)
    # Most are the true neighbours; the rest are almost as near.
    pairs = zip(approx.tolist(), true_knn.indices.tolist(), strict=True)
    hits = np.mean([len(set(a) & set(b)) / 8 for a, b in pairs])
    assert hits > 0.6
    assert float(found.median()) < 1.5 * float(true_knn.values.median())


def test_isometry_is_zero_for_a_rigid_motion_and_the_stretch_otherwise():
    from stg_node.avatar.gaussians import GaussianTable

    rng = torch.Generator().manual_seed(1)
    canonical = torch.rand(400, 3, generator=rng)
    table = GaussianTable({"means": canonical})
    graph = IsometryGraph(k=4)
    R = torch.as_tensor(
        Rotation.from_euler("xyz", [20, 40, 60], degrees=True).as_matrix(), dtype=torch.float32
    )
    moved = canonical @ R.T + torch.tensor([1.0, 2.0, 3.0])
    assert float(graph.loss(table, moved, canonical, None)) < 1e-4
    stretched = canonical * torch.tensor([1.1, 1.0, 1.0])
    # Each neighbour pair once, whichever of the two lists the other (a set of unordered pairs).
    lists = graph.neighbours.tolist()
    pairs = {tuple(sorted((i, j))) for i, row in enumerate(lists) for j in row if i != j}
    mutual = sum(1 for i, row in enumerate(lists) for j in row if i in lists[j])
    assert mutual > 0 and len(pairs) < 400 * 4  # the test sees pairs listed from both ends

    def stretch(i, j):
        return abs((stretched[i] - stretched[j]).norm() - (canonical[i] - canonical[j]).norm())

    got = float(graph.loss(table, stretched, canonical, None))
    assert got == pytest.approx(100.0 * float(np.mean([stretch(i, j) for i, j in pairs])), rel=1e-5)
    # Only the rows that were posed count: the others' edges are left out.
    index = torch.arange(0, 400, 2)
    partial = float(graph.loss(table, stretched[index], canonical[index], index))
    keep = [stretch(i, j) for i, j in pairs if i % 2 == 0 and j % 2 == 0]
    assert partial == pytest.approx(100.0 * float(np.mean(keep)), rel=1e-5)


def test_the_isometry_graph_is_rebuilt_after_a_prune_and_an_append_of_as_many_rows():
    """As the rigidity graph: a prune and an append leave the row count as it was (and the new means
    column may sit where a freed one was); the graph must follow the rows, checked by brute force."""
    from stg_node.avatar.gaussians import GaussianTable
    from stg_node.avatar.optim import TableOptimizer

    means = torch.tensor([[0.0, 0, 0], [0.01, 0, 0], [0.5, 0, 0], [1.0, 0, 0], [1.02, 0, 0]])
    table = GaussianTable({"means": means})
    opt = TableOptimizer(table, {"means": 0.1}, {})
    graph = IsometryGraph(k=1)
    points = table["means"].detach()
    graph.loss(table, points, points, None)
    built = graph.neighbours
    graph.loss(table, points, points, None)
    assert graph.neighbours is built  # unchanged rows: not rebuilt
    assert built[:, 0].tolist() == [1, 0, 1, 4, 3]
    opt.keep(torch.tensor([True, False, True, True, True]))  # row 1 (row 0's neighbour) goes
    opt.append({"means": torch.tensor([[0.52, 0, 0]])})  # and one beside row 2 (0.5) comes
    assert table.num == 5
    points = table["means"].detach()
    graph.loss(table, points, points, None)
    dist = torch.cdist(points, points).fill_diagonal_(float("inf"))
    assert graph.neighbours[:, 0].tolist() == dist.argmin(dim=1).tolist() == [1, 4, 3, 2, 1]


def test_models_and_configurations_from_before_shading_load_as_they_were_made(tiny_frames):
    """A snapshot or config.json without the shading settings is a model trained without them: it
    loads with the baked colour, spherical initial Gaussians and no cap, whatever today's defaults."""
    import dataclasses

    from avatar_helpers import small_config

    from stg_node.avatar.config import TrainConfig
    from stg_node.avatar.snapshot import model_from_snapshot
    from stg_node.avatar.trainer import Trainer

    trainer = Trainer(small_config(iterations=2), seed=0)
    trainer.add_frames(tiny_frames[:2])
    msg = trainer.snapshot()
    assert trainer.model.shading is not None and any(k.startswith("shading.") for k in msg.arrays)
    old = dataclasses.replace(
        msg,
        arrays={k: v for k, v in msg.arrays.items() if not k.startswith("shading.")},
        meta={
            k: v
            for k, v in msg.meta.items()
            if k not in ("model.shading", "model.init_flatness", "model.max_scale_ratio")
        },
    )
    model = model_from_snapshot(old)
    assert model.shading is None and model.config.max_scale_ratio == 0.0
    data = trainer.config.to_dict()
    for key in ("shading", "init_flatness", "max_scale_ratio"):
        del data["model"][key]
    del data["loss"]["isometry"]
    config = TrainConfig.from_dict(data)
    assert config.model.shading is False and config.model.init_flatness == 1.0
    assert config.loss.isometry == 0.0
    assert TrainConfig.from_dict(trainer.config.to_dict()) == trainer.config  # today's round-trips


def test_training_shades_outward_normals_and_renders_face_the_viewer(tiny_frames, monkeypatch):
    """model.normal_sign decides the sign of the normals training lights (towards the training
    camera by default, the disc's own side with "outward"); renders face every normal to the viewer;
    a configuration or snapshot from before the setting trained with normals facing the camera."""
    import dataclasses

    from avatar_helpers import small_config, spy_normal_signs

    from stg_node.avatar.config import TrainConfig
    from stg_node.avatar.renderer import AvatarRenderer
    from stg_node.avatar.snapshot import model_from_snapshot
    from stg_node.avatar.trainer import Trainer

    seen = spy_normal_signs(monkeypatch)
    signs = {}
    for sign in ("outward", "camera"):
        trainer = Trainer(small_config(iterations=2).replace(**{"model.normal_sign": sign}), seed=0)
        trainer.add_frames(tiny_frames[:2])
        seen.clear()
        trainer.step()
        signs[sign] = set(seen)
    assert signs == {"outward": {True}, "camera": {False}}
    assert small_config().model.normal_sign == "auto"  # the default decides (test_normal_trial.py)
    frame = tiny_frames[0]
    seen.clear()
    AvatarRenderer(trainer.model).render(frame.camera, frame.smpl, frame.time)
    assert seen == [False]
    # What an older model or configuration (no such setting) was trained with.
    msg = trainer.snapshot()
    old_meta = {k: v for k, v in msg.meta.items() if k != "model.normal_sign"}
    assert "model.normal_sign" in msg.meta
    assert model_from_snapshot(dataclasses.replace(msg, meta=old_meta)).config.normal_sign == "camera"
    data = trainer.config.to_dict()
    del data["model"]["normal_sign"]
    assert TrainConfig.from_dict(data).model.normal_sign == "camera"


def _unseen_share_by_sampling(direction: np.ndarray, towards: np.ndarray, samples: int = 400_000) -> float:
    """The part of a clamped-cosine lobe about ``direction`` on normals facing away from ``towards``,
    by Monte Carlo over uniform random directions (independent of the lattice the model uses)."""
    rng = np.random.default_rng(0)
    n = rng.normal(size=(samples, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    lobe = np.maximum(n @ direction, 0.0)
    return float((lobe * (n @ towards <= 0.0)).sum() / lobe.sum())


@pytest.mark.parametrize("angle_deg", [0.0, 60.0, 90.0, 120.0, 135.0, 180.0])
def test_the_unseen_penalty_charges_a_lamp_lighting_more_unseen_than_seen_normals(angle_deg):
    """One camera along +z: a lamp at angle theta from it pays its share of the mean irradiance
    times the excess of its lobe's part on the far hemisphere over the part on the near one, u - (1
    - u) with u against sampling: nothing up to 90 degrees, all of it facing away."""
    shading = Shading(light_count=1)
    towards = np.array([0.0, 0.0, 1.0])
    shading.add_view(torch.tensor([0.0, 0.0, 2.5]))  # only the direction counts
    t = math.radians(angle_deg)
    direction = np.array([math.sin(t), 0.0, math.cos(t)])
    light = shading.light
    with torch.no_grad():
        light.directions.copy_(torch.tensor(direction, dtype=torch.float32)[None])
        light.colors.fill_(0.5)
    a, c, _, mean = (v.detach() for v in light.parts())
    share = float((c[0] / 4.0 / mean).mean())
    expected = share * max(0.0, 2.0 * _unseen_share_by_sampling(direction, towards) - 1.0)
    penalty = float(shading.unseen_penalty().detach())
    assert penalty == pytest.approx(expected, abs=0.01 * share)
    if angle_deg <= 90.0:
        assert penalty < 0.01 * share
    if angle_deg == 180.0:
        assert penalty == pytest.approx(share, rel=1e-5)


def test_the_unseen_penalty_pulls_down_only_the_lamp_no_view_faces():
    """Its gradient pulls down the lamp pointing away from the camera and never the one pointing at
    it (that one only dilutes the other's share), and a second camera behind the subject sees that
    side and frees it again."""
    shading = Shading(light_count=2)
    shading.add_view(torch.tensor([0.0, 0.0, 1.0]))
    with torch.no_grad():
        shading.light.directions.copy_(torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]))
        shading.light.colors.fill_(0.0)
    shading.unseen_penalty().backward()
    grad = shading.light.colors.grad
    assert torch.all(grad[1] > 0) and torch.all(grad[0] <= 0)
    shading.add_view(torch.tensor([0.0, 0.0, -1.0]))
    assert float(shading.seen.min()) == 1.0 and float(shading.unseen_penalty().detach()) == 0.0


def test_training_marks_the_normals_its_cameras_face(tiny_frames):
    """The trainer counts each frame's view: the normals within 90 degrees of the direction from
    the body to the camera centre are seen, the others not; a snapshot keeps them, and one from
    before the buffer existed loads with every normal seen (no penalty)."""
    import dataclasses

    from avatar_helpers import small_config

    from stg_node.avatar.shading import SEEN_DIRECTIONS, sphere_directions
    from stg_node.avatar.snapshot import model_from_snapshot
    from stg_node.avatar.trainer import Trainer

    trainer = Trainer(small_config(iterations=2), seed=0)
    trainer.add_frames(tiny_frames[:3])
    dirs = sphere_directions(SEEN_DIRECTIONS).double().numpy()
    faced = np.zeros(SEEN_DIRECTIONS, bool)
    for f in tiny_frames[:3]:
        centre = -f.camera.R.T @ f.camera.t
        faced |= dirs @ (centre - np.asarray(f.smpl.Th).reshape(3)) > 0.0
    seen = trainer.model.shading.seen.numpy() > 0.5
    assert 0.4 < seen.mean() < 0.7 and np.array_equal(seen, faced)
    msg = trainer.snapshot()
    assert np.array_equal(model_from_snapshot(msg).shading.seen.numpy() > 0.5, faced)
    old = dataclasses.replace(msg, arrays={k: v for k, v in msg.arrays.items() if k != "shading.seen"})
    assert float(model_from_snapshot(old).shading.seen.min()) == 1.0
