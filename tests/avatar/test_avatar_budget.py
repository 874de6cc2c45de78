"""The Gaussian and step budget scaled with the person's size in pixels (stg_node.avatar.budget)."""

from __future__ import annotations

import numpy as np
import pytest

from stg_node.avatar.budget import (
    MAX_SCALE,
    MIN_PIXEL_SCALE_AREA,
    REFERENCE_AREA_PX,
    SCALED,
    person_size,
    scale_budget,
)
from stg_node.avatar.presets import preset


def person(height: int, width: int, image: int = 600) -> np.ndarray:
    mask = np.zeros((image, image), np.uint8)
    mask[10 : 10 + height, 10 : 10 + width] = 255
    return mask


def test_person_size_is_the_median_over_frames_and_ignores_empty_masks():
    masks = [person(100, 40), person(200, 50), person(300, 60), np.zeros((600, 600), np.uint8), None]
    assert person_size(masks) == (200 * 50, 200)


def test_a_person_twice_the_reference_area_gets_the_hand_computed_budget():
    # 400 x 100 px = 40,000 px = 2 x the reference: Gaussians x 2, steps and pixel settings x sqrt(2),
    # the flow weight / sqrt(2); the values written out by hand from the fast preset.
    fast = preset("fast")
    assert REFERENCE_AREA_PX == 20_000
    config, budget = scale_budget(fast, [person(400, 100)] * 3)
    assert (budget.scale, budget.person_area_px, budget.person_height_px) == (2.0, 40_000, 400)
    assert budget.steps_scale == budget.pixel_scale == pytest.approx(1.414214, abs=1e-6)
    assert (config.model.num_gaussians, config.model.max_gaussians) == (24_000, 60_000)
    assert (config.densify.flow_max_new, config.iterations) == (600, 2121)  # 1500 x 1.41421 = 2121.3
    assert config.densify.motion_floor_px == pytest.approx(1.414214, abs=1e-6)
    assert config.densify.flow_consistency_px == pytest.approx(2.121320, abs=1e-6)
    assert config.densify.residual_motion_px == pytest.approx(2.121320, abs=1e-6)
    assert config.densify.motion_min_px == pytest.approx(8.485281, abs=1e-6)
    assert config.crop_margin_px == 23  # 16 x 1.41421 = 22.6
    assert config.loss.flow == pytest.approx(0.035355, abs=1e-6)
    # what judges the image pixel by pixel stays (the module docstring says why)
    assert config.densify.grad_threshold == fast.densify.grad_threshold
    assert config.densify.region_px == fast.densify.region_px
    assert config.loss.ssim == fast.loss.ssim
    assert set(budget.changes) == set(SCALED)
    config.validate()


def test_a_smaller_person_keeps_the_gaussians_and_steps_but_its_motion_thresholds_follow_it_down():
    # 100 x 50 px = 5,000 px = a quarter of the reference (the benchmark's person at 256 px): half the
    # linear size, so the settings that measure the body's motion in pixels halve (the same motion in
    # metres) and the flow weight doubles; the Gaussians and the steps stay the preset's. Values by hand.
    fast = preset("fast")
    config, budget = scale_budget(fast, [person(100, 50)])
    assert (budget.scale, budget.steps_scale, budget.pixel_scale) == (1.0, 1.0, 0.5)
    assert budget.changes == {
        "densify.motion_floor_px": 0.5,
        "densify.flow_consistency_px": 0.75,
        "densify.residual_motion_px": 0.75,
        "densify.motion_min_px": 3.0,
        "crop_margin_px": 8,
        "loss.flow": 0.1,
    }
    model = config.model
    assert (model.num_gaussians, model.max_gaussians, config.iterations) == (12_000, 30_000, 1500)
    assert config.densify.flow_max_new == fast.densify.flow_max_new
    # half the reference's area: x sqrt(0.5)
    config, budget = scale_budget(fast, [person(100, 100)])
    assert budget.pixel_scale == pytest.approx(0.707107, abs=1e-6)
    assert config.densify.residual_motion_px == pytest.approx(1.06066, abs=1e-5)
    assert config.crop_margin_px == 11  # 16 x 0.7071 = 11.3
    # smaller than a quarter: held at half the reference's linear size (MIN_PIXEL_SCALE_AREA)
    assert MIN_PIXEL_SCALE_AREA == 0.25
    config, budget = scale_budget(fast, [person(50, 20)])
    assert budget.pixel_scale == 0.5 and config.densify.residual_motion_px == 0.75
    config.validate()


def test_huge_people_are_capped():
    fast = preset("fast")
    config, budget = scale_budget(fast, [person(590, 580)])
    assert budget.scale == MAX_SCALE and config.iterations == 2 * fast.iterations
    assert config.model.max_gaussians == 4 * fast.model.max_gaussians and budget.pixel_scale == 2.0
    assert config.densify.motion_min_px == 2 * fast.densify.motion_min_px


def test_what_the_user_set_is_kept():
    fast = preset("fast").replace(iterations=777)
    config, budget = scale_budget(fast, [person(400, 200)], fixed=("iterations", "model.max_gaussians"))
    assert config.iterations == 777 and config.model.max_gaussians == fast.model.max_gaussians
    assert config.model.num_gaussians > fast.model.num_gaussians
    assert "iterations" not in budget.changes
    config, budget = scale_budget(fast, [person(400, 200)], fixed=("densify.motion_min_px", "loss.flow"))
    assert config.densify.motion_min_px == fast.densify.motion_min_px and config.loss.flow == fast.loss.flow
    assert config.densify.residual_motion_px > fast.densify.residual_motion_px


def test_no_masks_no_change():
    fast = preset("fast")
    assert scale_budget(fast, [None, np.zeros((8, 8), np.uint8)])[0] == fast
