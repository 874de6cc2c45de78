"""The trainer node's ``flow_level`` reaches the frame store that computes each new pair's flow."""

from __future__ import annotations

import numpy as np

from stg_node.data.flow import compute_flow_pair
from stg_node.nodes.avatar_adapter import TrainerAdapter
from stg_node.nodes.trainer import TrainerParams


def test_the_live_trainer_computes_its_flow_at_the_level_asked():
    assert TrainerParams().flow_level == 2  # the live default: a quarter resolution
    offline = TrainerAdapter.create()._trainer.store.flow_settings
    live = TrainerAdapter.create(flow_level=TrainerParams().flow_level)._trainer.store.flow_settings
    assert offline.finest_scale == 0 and live.finest_scale == 2
    # The level is what the flow is computed with: a textured square moved 3 px right.
    rng = np.random.default_rng(0)
    a = np.zeros((96, 96, 3), np.uint8)
    a[24:72, 24:72] = rng.integers(0, 255, (48, 48, 3), np.uint8)
    b = np.roll(a, 3, axis=1)
    mask = np.zeros((96, 96), np.uint8)
    mask[20:76, 20:80] = 255
    exact = compute_flow_pair(a, b, mask, mask, offline).forward[30:66, 30:66, 0]
    coarse = compute_flow_pair(a, b, mask, mask, live).forward[30:66, 30:66, 0]
    assert abs(float(np.median(exact)) - 3.0) < 0.25
    assert not np.array_equal(exact, coarse)
