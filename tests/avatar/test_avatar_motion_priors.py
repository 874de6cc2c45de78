"""The non-rigid remedies for a single camera: the line-of-sight penalty against hand-computed cases,
shared motion bases in closed form (interpolation, derivative, growth, the snapshot round trip)."""

from __future__ import annotations

import math

import pytest
import torch

from stg_node.avatar import spacetime
from stg_node.avatar.motion_basis import MotionBases, initial_coefficients
from stg_node.avatar.motion_priors import line_of_sight, world_offsets


def test_line_of_sight_penalises_the_component_along_the_camera_ray_only():
    """Camera at (0, 0, -2); a Gaussian at the origin sees the ray (0, 0, 1): an offset (3, 4, 5) cm
    costs 5 cm. A second at (2, 0, 0) lies on the ray (1, 0, 1)/sqrt(2): offset (1, 0, 0) cm costs
    1/sqrt(2) cm, (1, 0, -1) cm costs 0 (across the ray), (1, 0, 1) cm costs sqrt(2)."""
    camera = torch.tensor([0.0, 0.0, -2.0])
    posed = torch.tensor([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    cm = 0.01
    d = torch.tensor([[3.0, 4.0, 5.0], [1.0, 0.0, 0.0]]) * cm
    assert float(line_of_sight(d, posed, camera)) == pytest.approx((5.0 + 1 / math.sqrt(2)) / 2, rel=1e-5)
    d2 = torch.tensor([[3.0, 4.0, 0.0], [1.0, 0.0, -1.0]]) * cm  # across both rays: free
    assert float(line_of_sight(d2, posed, camera)) == pytest.approx(0.0, abs=1e-6)
    d3 = torch.tensor([[0.0, 0.0, -2.0], [1.0, 0.0, 1.0]]) * cm  # sign does not matter
    assert float(line_of_sight(d3, posed, camera)) == pytest.approx((2.0 + math.sqrt(2)) / 2, rel=1e-5)
    # Presence weights: a copy absent at this instant does not count.
    presence = torch.tensor([0.0, 1.0])
    assert float(line_of_sight(d, posed, camera, presence)) == pytest.approx(1 / math.sqrt(2), rel=1e-5)
    # Its gradient moves the offset along the ray only.
    d = d.clone().requires_grad_(True)
    line_of_sight(d, posed, camera).backward()
    ray = torch.tensor([[0.0, 0.0, 1.0], [1 / math.sqrt(2), 0.0, 1 / math.sqrt(2)]])
    assert torch.allclose(torch.linalg.cross(d.grad, ray), torch.zeros(2, 3), atol=1e-6)
    assert float(line_of_sight(torch.zeros(0, 3), torch.zeros(0, 3), camera)) == 0.0


def test_world_offsets_turn_with_the_blended_bones():
    """One bone rotated 90 degrees about z: a canonical offset (1, 0, 0) becomes (0, 1, 0) in the world."""
    from stg_node.avatar.rigid import PosedBones

    transforms = torch.eye(4).repeat(1, 24, 1, 1)
    transforms[0, 3, :3, :3] = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    transforms[0, 3, :3, 3] = torch.tensor([5.0, 6.0, 7.0])  # translation does not move an offset
    bones = PosedBones(transforms, torch.zeros(1, 24, 4))
    weights = torch.zeros(2, 24)
    weights[0, 3] = 1.0
    weights[1, 0] = 1.0
    out = world_offsets(torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]), weights, bones)
    assert torch.allclose(out, torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]), atol=1e-6)


def test_bases_interpolate_linearly_between_knots_and_hold_beyond_them():
    values = torch.arange(2 * 4 * 12, dtype=torch.float32).reshape(2, 4, 3, 4)
    bases = MotionBases(2, knot_units=0.5, values=values)
    assert torch.equal(bases.at(0.5), values[:, 1])
    assert torch.allclose(bases.at(0.6), 0.8 * values[:, 1] + 0.2 * values[:, 2])
    assert torch.equal(bases.at(-3.0), values[:, 0]) and torch.equal(bases.at(99.0), values[:, 3])
    assert torch.equal(bases.at(1.5), values[:, 3])  # the last knot itself
    assert torch.allclose(bases.derivative(0.6), (values[:, 2] - values[:, 1]) / 0.5)
    assert torch.equal(bases.derivative(5.0), torch.zeros(2, 3, 4))
    # Growing to cover a later time repeats the last knot (continuous) and keeps the rest.
    assert bases.grown(1.4) is None
    grown = bases.grown(2.6)
    assert grown.shape == (2, 7, 3, 4) and torch.equal(grown[:, :4], values)
    assert torch.equal(grown[:, 4:], values[:, 3:4].expand(2, 3, 3, 4))
    ramp = torch.zeros(1, 3, 3, 4)
    ramp[0, :, 0, 3] = torch.tensor([0.0, 1.0, 2.0])  # a translation growing linearly in time
    assert float(MotionBases(1, 1.0, values=ramp).roughness().detach()) == 0.0  # no second difference
    with pytest.raises(ValueError, match="motion bases must be"):
        MotionBases(3, 0.5, values=values)


def test_an_affine_basis_moves_a_point_by_its_matrix_and_mixtures_add():
    """A = [[0, -1, 0, 0.1], [1, 0, 0, 0], [0, 0, 0, 0]] maps (1, 2, 3) to (-2 + 0.1, 1, 0); a second
    basis translating by (0, 0, 1) mixed in at 0.5 adds (0, 0, 0.5)."""
    motions = torch.zeros(2, 3, 4)
    motions[0, 0] = torch.tensor([0.0, -1.0, 0.0, 0.1])
    motions[0, 1] = torch.tensor([1.0, 0.0, 0.0, 0.0])
    motions[1, 2, 3] = 1.0
    points = torch.tensor([[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]])
    coef = torch.tensor([[1.0, 0.5], [0.0, 2.0]])
    out = MotionBases.apply(motions, coef, points)
    assert torch.allclose(out, torch.tensor([[-1.9, 1.0, 0.5], [0.0, 0.0, 2.0]]))
    # Each Gaussian starts with its skinning weights summed per basis (bones 0-11 -> 0, 12-23 -> 1).
    weights = torch.zeros(2, 24)
    weights[0, [3, 16]] = torch.tensor([0.25, 0.75])
    weights[1, 23] = 1.0
    assert torch.allclose(initial_coefficients(weights, 2), torch.tensor([[0.25, 0.75], [0.0, 1.0]]))
    assert torch.equal(initial_coefficients(weights, 24), weights)


def test_offsets_from_bases_are_the_coefficient_mix_and_skipping_changes_nothing():
    from stg_node.avatar.config import ModelConfig
    from stg_node.avatar.gaussians import GaussianTable, new_columns

    cfg = ModelConfig(num_gaussians=6, max_gaussians=10, motion_basis=3)
    gen = torch.Generator().manual_seed(1)
    cols = new_columns(
        cfg, torch.randn(6, 3, generator=gen), torch.softmax(torch.randn(6, 24, generator=gen), 1), 0.01
    )
    assert "motion" not in cols and cols["motion_coef"].shape == (6, 3)
    cols["motion_coef"] = torch.randn(6, 3, generator=gen)
    cols["motion_coef"][[1, 4]] = 0.0
    table = GaussianTable(cols)
    bases = MotionBases(3, 0.1, values=torch.randn(3, 5, 3, 4, generator=gen) * 0.01)
    u = 0.23
    st = spacetime.evaluate(table, u, cfg.time_horizon, temporal_opacity=True, bases=bases)
    assert torch.allclose(st.offsets, MotionBases.apply(bases.at(u), table["motion_coef"], table["means"]))
    skipped = spacetime.evaluate(
        table, u, cfg.time_horizon, temporal_opacity=True, bases=bases, skip_inactive=True
    )
    assert torch.allclose(skipped.offsets, st.offsets) and torch.equal(
        skipped.offsets[[1, 4]], torch.zeros(2, 3)
    )
    eps = 1e-3
    numeric = (
        spacetime.evaluate(table, u + eps, 1.0, temporal_opacity=False, bases=bases).offsets
        - spacetime.evaluate(table, u - eps, 1.0, temporal_opacity=False, bases=bases).offsets
    ) / (2 * eps)
    assert torch.allclose(spacetime.velocity(table, u, 1.0, bases), numeric, atol=1e-4)
