"""The avatar's ambient-occlusion term (stg_node/avatar/occlusion.py) against closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from stg_node.avatar.occlusion import BodyOcclusion, fit_spheres, sphere_visibility
from stg_node.avatar.shading import Shading


def _cosine_hemisphere(n: int, seed: int = 0) -> np.ndarray:
    """Cosine-weighted directions around +z (Malley's method)."""
    rng = np.random.default_rng(seed)
    u1, u2 = rng.random(n), rng.random(n)
    r, phi = np.sqrt(u1), 2.0 * math.pi * u2
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1.0 - u1)], axis=1)


def _hits_sphere(dirs: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """Whether rays from the origin along ``dirs`` hit the sphere (ray-sphere intersection)."""
    along = dirs @ centre
    closest2 = centre @ centre - along**2
    return (along > 0) & (closest2 <= radius**2)


@pytest.mark.parametrize(
    "centre, radius",
    [((0.0, 0.0, 1.0), 0.3), ((0.5, 0.2, 0.6), 0.25), ((0.8, 0.0, 0.5), 0.2), ((0.0, 0.0, 0.3), 0.29)],
)
def test_one_sphere_covers_its_form_factor_of_the_sky(centre, radius):
    """A sphere wholly above a point's horizon covers ``cos(theta) (r / d)^2`` of its cosine-weighted
    hemisphere: checked against rays cast from the point (an independent count)."""
    c = np.asarray(centre)
    assert c[2] > radius  # above the horizon: the formula is exact
    dirs = _cosine_hemisphere(400_000)
    truth = 1.0 - _hits_sphere(dirs, c, radius).mean()
    got = sphere_visibility(
        torch.zeros(1, 3, dtype=torch.float64),
        torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64),
        torch.tensor([centre], dtype=torch.float64),
        torch.tensor([radius], dtype=torch.float64),
    )
    assert float(got[0]) == pytest.approx(truth, abs=0.004)


def test_spheres_behind_the_horizon_or_switched_off_do_not_occlude():
    points = torch.zeros(2, 3)
    normals = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    centres = torch.tensor([[0.0, 0.0, 1.0]])
    radii = torch.tensor([0.5])
    visible = sphere_visibility(points, normals, centres, radii)
    assert float(visible[0]) == pytest.approx(0.75, abs=1e-6) and float(visible[1]) == 1.0
    off = sphere_visibility(points, normals, centres, radii, torch.zeros(2, 1, dtype=torch.bool))
    assert torch.equal(off, torch.ones(2))


def test_spheres_fitted_to_a_cylinder_have_its_radius_and_tile_its_axis():
    """A closed-form body: a cylinder of radius 5 cm and length 40 cm, all on one bone."""
    theta, z = np.meshgrid(np.linspace(0, 2 * math.pi, 64, endpoint=False), np.linspace(0.0, 0.4, 81))
    pts = np.stack([0.05 * np.cos(theta), 0.05 * np.sin(theta), z], axis=-1).reshape(-1, 3) + [1.0, 2.0, 0.0]
    weights = torch.zeros(pts.shape[0], 3)
    weights[:, 1] = 1.0
    centres, radii, bones = fit_spheres(torch.tensor(pts), weights)
    assert bones.tolist() == [1] * 4  # length / (2 r) = 4 chunks
    np.testing.assert_allclose(radii.numpy(), 0.05, rtol=1e-3)
    np.testing.assert_allclose(centres[:, :2].numpy(), [[1.0, 2.0]] * 4, atol=1e-4)
    np.testing.assert_allclose(np.sort(centres[:, 2].numpy()), [0.05, 0.15, 0.25, 0.35], atol=0.01)


def _two_bone_occlusion() -> BodyOcclusion:
    """Bone 0 a ball of radius 0.2 at the origin, bone 1 its child, bone 2 unrelated (a ball at x = 1)."""
    occ = BodyOcclusion()
    ball = torch.nn.functional.normalize(
        torch.randn(500, 3, generator=torch.Generator().manual_seed(0)), dim=1
    )
    vertices = torch.cat(
        [0.2 * ball, 0.2 * ball + torch.tensor([0.0, 0.0, 3.0]), 0.2 * ball + torch.tensor([1.0, 0, 0])]
    )
    weights = torch.zeros(1500, 3)
    for bone in range(3):
        weights[500 * bone : 500 * (bone + 1), bone] = 1.0
    occ.fit(vertices, weights, parents=[-1, 0, -1])
    return occ


def test_the_spheres_move_with_their_bones_and_skip_the_gaussians_own_and_neighbouring_bones():
    occ = _two_bone_occlusion()
    assert occ.radii.shape[0] == 3
    point = torch.tensor([[0.0, 0.0, 0.5]])
    down = torch.tensor([[0.0, 0.0, -1.0]])  # facing the ball of bone 0, 0.5 m away
    rest = torch.eye(4).expand(3, 4, 4)

    def form_factor(bone):  # cos(theta) (r / d)^2 of the fitted sphere of ``bone`` (one each here)
        c = occ.centres[occ.bones == bone][0].double().numpy() - point[0].double().numpy()
        d = np.linalg.norm(c)
        return max(0.0, -c[2] / d) * (float(occ.radii[occ.bones == bone][0]) / d) ** 2

    # a Gaussian of the unrelated bone 2 sees bone 0's ball (bone 1's is behind it); one of bone 0
    # or of its child bone 1 sees only bone 2's
    seen = occ.visibility(point.expand(3, 3), down.expand(3, 3), torch.tensor([2, 0, 1]), rest)
    expected = [1.0 - form_factor(0), 1.0 - form_factor(2), 1.0 - form_factor(2)]
    assert form_factor(0) > 0.1 and form_factor(1) == 0.0
    np.testing.assert_allclose(seen.numpy(), expected, rtol=1e-5)
    # bone 0 moved 10 m away: nothing left in the way
    moved = rest.clone()
    moved[0, 0, 3] = 10.0
    assert float(occ.visibility(point, down, torch.tensor([2]), moved)[0]) == pytest.approx(1.0, abs=1e-3)


def test_the_term_scales_the_irradiance_by_its_strength_and_round_trips():
    shading = Shading("distant", 2, occlusion=True)
    shading.occlusion.load_state_dict(_two_bone_occlusion().state_dict())  # resizes to the stored spheres
    assert shading.occlusion.fitted
    albedo = torch.rand(4, 3)
    normals = torch.nn.functional.normalize(torch.randn(4, 3), dim=1)
    plain = shading(albedo, normals)
    visible = torch.tensor([1.0, 0.5, 0.0, 0.25])
    k = float(shading.occlusion.strength().detach())
    assert k == pytest.approx(0.5)
    got = shading(albedo, normals, visible=visible)
    np.testing.assert_allclose(
        got.detach().numpy(), (plain * (1 - k + k * visible)[:, None]).detach().numpy(), rtol=1e-6
    )
    assert torch.equal(shading(albedo, normals, visible=torch.ones(4)), plain)


def test_a_trained_model_with_occlusion_renders_the_same_after_a_snapshot(tiny_frames):
    from avatar_helpers import small_config

    from stg_node.avatar.model import BodyState, Camera3
    from stg_node.avatar.snapshot import model_from_snapshot
    from stg_node.avatar.trainer import Trainer

    config = small_config(iterations=3)  # the term is on by default
    trainer = Trainer(config, seed=0)
    trainer.add_frames(tiny_frames[:2])
    strength = float(trainer.model.shading.occlusion.strength().detach())
    for _ in range(3):
        trainer.step()
    model = trainer.model
    assert float(model.shading.occlusion.strength().detach()) != strength  # it learns with the light
    assert model.shading.occlusion.fitted and model.shading.occlusion.radii.shape[0] > 20
    frame = tiny_frames[0]
    body = BodyState.from_smpl(frame.smpl)
    camera = Camera3.from_camera(frame.camera)
    with torch.no_grad():
        posed = model.pose(body, 0.0, camera.center)
        again = model_from_snapshot(trainer.snapshot()).pose(body, 0.0, camera.center)
    torch.testing.assert_close(posed.colors, again.colors)
    # the occlusion darkens somewhere (armpits, between the legs) and never brightens
    model.shading.occlusion.strength_logit.data.fill_(10.0)
    with torch.no_grad():
        dark = model.pose(body, 0.0, camera.center).colors
        model_off = model.shading.occlusion
        model.shading.occlusion = None
        bright = model.pose(body, 0.0, camera.center).colors
        model.shading.occlusion = model_off
    assert bool((dark <= bright + 1e-6).all()) and float((bright - dark).max()) > 0.05


def test_the_spheres_agree_with_the_bodys_own_ambient_occlusion():
    """A second implementation: the sphere proxy's visible share at the open body's vertices against
    the mesh's ambient occlusion by depth maps (stg_node.data.synth.occlusion), arms lowered so that
    they stand beside the torso."""
    from stg_node.body import load_body_model
    from stg_node.data.synth.mesh_raster import vertex_normals
    from stg_node.data.synth.occlusion import ambient_occlusion

    body = load_body_model()
    poses = torch.zeros(1, 72)
    poses[0, 16 * 3 + 2] = -1.2  # left shoulder down
    poses[0, 17 * 3 + 2] = 1.2  # right shoulder down
    with torch.no_grad():
        posed = body(betas=torch.zeros(1, 10), poses=poses, Rh=torch.zeros(1, 3), Th=torch.zeros(1, 3))
        rest = body(
            betas=torch.zeros(1, 10), poses=torch.zeros(1, 72), Rh=torch.zeros(1, 3), Th=torch.zeros(1, 3)
        )
    faces = torch.as_tensor(np.asarray(body.faces)).long()
    vertices = posed.vertices[0].float()
    normals = vertex_normals(vertices, faces)
    occ = BodyOcclusion()
    occ.fit(rest.vertices[0], body.weights, [int(p) for p in body.parents])
    # fitted to the rest mesh, posed by the bones' rest -> world transforms
    visible = occ.visibility(vertices, normals, body.weights.argmax(dim=1), posed.bone_transforms[0].float())
    truth = ambient_occlusion(vertices, normals, vertices, faces, directions=32)
    assert np.corrcoef(truth.numpy(), visible.numpy())[0, 1] > 0.5


# --- the C++ kernel (csrc/sphere_occlusion.cpp) against the torch reference ---------------------


def _random_spheres(seed: int, points: int, spheres: int, groups: int):
    """Points around and inside spheres (some exactly at a centre), unit normals, a random mask."""
    g = torch.Generator().manual_seed(seed)
    centres = torch.randn(spheres, 3, generator=g, dtype=torch.float64) * 0.3
    radii = 0.02 + 0.1 * torch.rand(spheres, generator=g, dtype=torch.float64)
    p = torch.randn(points, 3, generator=g, dtype=torch.float64) * 0.4
    p[: spheres // 2] = centres[: spheres // 2]  # at a centre: d^2 clamped, the share capped at 1
    p[spheres // 2 : spheres] = (
        centres[: spheres - spheres // 2] + 0.5 * radii[: spheres - spheres // 2, None]
    )
    n = torch.nn.functional.normalize(torch.randn(points, 3, generator=g, dtype=torch.float64), dim=1)
    mask = torch.rand(groups, spheres, generator=g) > 0.3
    group = torch.randint(0, groups, (points,), generator=g)
    return p, n, centres, radii, mask, group


@pytest.mark.parametrize("spheres", [1, 7, 8, 13, 71])
def test_the_kernel_equals_the_torch_reference_in_float64(cpu_kernels, spheres):
    """The kernel (float32, eight spheres a lane group, padded) against ``sphere_visibility`` in float64,
    for sphere counts below, at and past a multiple of eight."""
    p, n, c, r, mask, group = _random_spheres(spheres, 600, spheres, 5)
    truth = sphere_visibility(p, n, c, r, mask[group])
    got = cpu_kernels.ops.sphere_visibility(
        p.float(), n.float(), group, c.float(), r.square().float(), mask.float(), 1
    )
    assert got.dtype == torch.float32 and got.shape == (600,)
    assert float(truth.min()) < 0.9  # the case covers points in the spheres' shadow
    np.testing.assert_allclose(got.double().numpy(), truth.numpy(), atol=2e-6, rtol=0)
    two = cpu_kernels.ops.sphere_visibility(
        p.float(), n.float(), group, c.float(), r.square().float(), mask.float(), 2
    )
    assert torch.equal(two, got)  # threads split the points, never a point's product


@pytest.mark.parametrize("points", [601, 600])  # an odd point out of the pairs, and none
def test_the_avx512_pairs_equal_the_eight_lane_points_bit_for_bit(cpu_kernels, points, monkeypatch):
    """On an AVX-512 CPU the kernel takes two points per 16-lane vector (sphere_occlusion.cpp,
    visibility_pair); STG_SPLAT_NO_AVX512 keeps one point per 8 lanes: the same visibility to the bit
    (on other CPUs both runs take the 8-lane path)."""
    p, n, c, r, mask, group = _random_spheres(71, points, 12, 9)
    args = (p.float(), n.float(), group, c.float(), r.square().float(), mask.float(), 1)
    monkeypatch.setenv("STG_SPLAT_NO_AVX512", "1")
    narrow = cpu_kernels.ops.sphere_visibility(*args)
    monkeypatch.setenv("STG_SPLAT_NO_AVX512", "0")
    assert torch.equal(cpu_kernels.ops.sphere_visibility(*args), narrow)


def test_body_occlusion_takes_the_kernel_and_agrees_with_its_reference(cpu_kernels):
    """BodyOcclusion.visibility: float32 CPU tensors go to the kernel, the same call under
    ``kernels.reference()`` (and in float64) to torch; posed spheres, own and neighbouring bones left out."""
    from stg_node.avatar import kernels

    occ = _two_bone_occlusion()
    g = torch.Generator().manual_seed(3)
    points = torch.randn(500, 3, generator=g) * 0.5
    normals = torch.nn.functional.normalize(torch.randn(500, 3, generator=g), dim=1)
    bone = torch.randint(0, 3, (500,), generator=g)
    transforms = torch.eye(4).repeat(3, 1, 1)
    transforms[1, :3, 3] = torch.tensor([0.0, 0.3, -2.8])  # the child ball swung down beside the first
    fast = occ.visibility(points, normals, bone, transforms)
    with kernels.reference():
        ref = occ.visibility(points, normals, bone, transforms)
    exact = occ.visibility(points.double(), normals.double(), bone, transforms.double())
    assert float(exact.min()) < 0.7 and float(exact.max()) == 1.0
    np.testing.assert_allclose(fast.double().numpy(), exact.numpy(), atol=2e-6)
    np.testing.assert_allclose(ref.double().numpy(), exact.numpy(), atol=1e-4)  # torch's float32 cancels
    assert occ.visibility(points[:0], normals[:0], bone[:0], transforms).shape == (0,)


def test_the_kernel_refuses_a_group_outside_its_mask(cpu_kernels):
    p, n, c, r, mask, group = _random_spheres(0, 10, 4, 2)
    group[3] = 2
    with pytest.raises(RuntimeError, match="group 2 of point 3"):
        cpu_kernels.ops.sphere_visibility(
            p.float(), n.float(), group, c.float(), r.square().float(), mask.float(), 1
        )


# --- the default --------------------------------------------------------------------------------


def test_every_preset_casts_the_body_on_itself():
    """On by default (docs/AVATAR.md, "What the body casts on itself"): every preset's model has the
    term, and a trainer fits its spheres."""
    from stg_node.avatar import preset
    from stg_node.avatar.config import ModelConfig

    assert ModelConfig().occlusion is True
    for name in ("fast", "balanced", "quality"):
        assert preset(name).model.occlusion is True, name


def test_a_model_from_before_the_term_loads_and_renders_without_it(tiny_frames):
    """A snapshot written before the term existed (no ``model.occlusion`` in its meta, no spheres)
    loads with the term off and renders as the model it was."""
    import dataclasses

    from avatar_helpers import small_config

    from stg_node.avatar.config import TrainConfig
    from stg_node.avatar.model import BodyState, Camera3
    from stg_node.avatar.snapshot import model_from_snapshot
    from stg_node.avatar.trainer import Trainer

    trainer = Trainer(small_config(iterations=2).replace(**{"model.occlusion": False}), seed=0)
    trainer.add_frames(tiny_frames[:2])
    trainer.step()
    msg = trainer.snapshot()
    assert not any(".occlusion." in name for name in msg.arrays)  # what an older writer wrote
    old = dataclasses.replace(msg, meta={k: v for k, v in msg.meta.items() if k != "model.occlusion"})
    model = model_from_snapshot(old)
    assert model.config.occlusion is False and model.shading.occlusion is None
    frame = tiny_frames[0]
    body, camera = BodyState.from_smpl(frame.smpl), Camera3.from_camera(frame.camera)
    with torch.no_grad():
        torch.testing.assert_close(
            model.pose(body, 0.0, camera.center).colors, trainer.model.pose(body, 0.0, camera.center).colors
        )
    data = trainer.config.to_dict()
    del data["model"]["occlusion"]
    assert TrainConfig.from_dict(data).model.occlusion is False
