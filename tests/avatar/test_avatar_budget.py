"""The Gaussian and step budget scaled with the person's size in pixels (stg_node.avatar.budget)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stg_node.avatar.budget import MAX_SCALE, REFERENCE_AREA_PX, person_size, scale_budget
from stg_node.avatar.presets import preset


def person(height: int, width: int, image: int = 600) -> np.ndarray:
    mask = np.zeros((image, image), np.uint8)
    mask[10 : 10 + height, 10 : 10 + width] = 255
    return mask


def test_person_size_is_the_median_over_frames_and_ignores_empty_masks():
    masks = [person(100, 40), person(200, 50), person(300, 60), np.zeros((600, 600), np.uint8), None]
    assert person_size(masks) == (200 * 50, 200)


def test_a_person_twice_the_reference_area_gets_twice_the_gaussians_and_sqrt2_the_steps():
    fast = preset("fast")
    height = 400
    width = round(2 * REFERENCE_AREA_PX / height)
    config, budget = scale_budget(fast, [person(height, width)])
    assert budget.scale == pytest.approx(2.0, rel=0.01)
    assert config.model.num_gaussians == pytest.approx(2 * fast.model.num_gaussians, rel=0.01)
    assert config.model.max_gaussians == pytest.approx(2 * fast.model.max_gaussians, rel=0.01)
    assert config.iterations == pytest.approx(math.sqrt(2) * fast.iterations, rel=0.01)
    assert set(budget.changes) == {
        "model.num_gaussians",
        "model.max_gaussians",
        "densify.flow_max_new",
        "iterations",
    }


def test_small_people_keep_the_preset_and_huge_ones_are_capped():
    fast = preset("fast")
    config, budget = scale_budget(fast, [person(100, 50)])
    assert config == fast and budget.changes == {} and budget.scale == 1.0
    config, budget = scale_budget(fast, [person(590, 580)])
    assert budget.scale == MAX_SCALE and config.iterations == 2 * fast.iterations


def test_what_the_user_set_is_kept():
    fast = preset("fast").replace(iterations=777)
    config, budget = scale_budget(fast, [person(400, 200)], fixed=("iterations", "model.max_gaussians"))
    assert config.iterations == 777 and config.model.max_gaussians == fast.model.max_gaussians
    assert config.model.num_gaussians > fast.model.num_gaussians
    assert "iterations" not in budget.changes


def test_no_masks_no_change():
    fast = preset("fast")
    assert scale_budget(fast, [None, np.zeros((8, 8), np.uint8)])[0] == fast
