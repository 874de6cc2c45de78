"""tools/shading_oracles.py: the true light it swaps in is the subject's, at the learned light's scale."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

import shading_oracles  # noqa: E402


def _subject(tmp_path: Path, shading: dict) -> Path:
    from stg_node.data.synth.writer import METADATA_FILE, METADATA_FORMAT, METADATA_VERSION

    record = {"format": METADATA_FORMAT, "version": METADATA_VERSION, "shading": shading}
    (tmp_path / METADATA_FILE).write_text(json.dumps(record))
    return tmp_path


def test_the_true_light_is_the_subjects_scaled_to_a_mean_irradiance_of_one(tmp_path):
    direction = np.array([0.75, -0.4, 0.5]) / np.linalg.norm([0.75, -0.4, 0.5])
    room = {
        "mode": "room",
        "ambient": [0.3, 0.3, 0.3],
        "sky": 0.0,
        "lights": [{"direction": direction.tolist(), "color": [0.7, 0.6, 0.5], "frame": "world"}],
    }
    light, mean = shading_oracles.true_light(_subject(tmp_path, room))
    # Monte Carlo over the sphere: the subject's own shade, and the oracle light's mean.
    normals = torch.nn.functional.normalize(
        torch.randn(200_000, 3, generator=torch.Generator().manual_seed(0)), dim=1
    )
    shade = 0.3 + (normals.double().numpy() @ direction).clip(min=0)[:, None] * np.array([0.7, 0.6, 0.5])
    np.testing.assert_allclose(mean, shade.mean(axis=0), rtol=0.01)
    oracle = light.irradiance(normals).numpy()
    np.testing.assert_allclose(oracle.mean(axis=0), 1.0, rtol=0.01)
    np.testing.assert_allclose(oracle * mean, shade, atol=1e-5)  # the same light, scaled


def test_lights_that_are_not_fixed_in_the_world_have_no_oracle(tmp_path):
    body = {
        "mode": "lambert",
        "ambient": [0.45] * 3,
        "lights": [{"direction": [0, 0, 1], "color": [0.55] * 3, "frame": "body"}],
    }
    with pytest.raises(ValueError, match="turning with the body"):
        shading_oracles.true_light(_subject(tmp_path, body))
