"""Fixtures for the tracking tests: the open body and small synthetic sequences with ground truth."""

from __future__ import annotations

import pytest
from trackhelpers import load_ground_truth

from stg_node.body import load_body_model
from stg_node.data.synth import SynthConfig, generate


@pytest.fixture(scope="session")
def body():
    return load_body_model()


@pytest.fixture(scope="session")
def synth_small(tmp_path_factory, body):
    """48 frames of the mixed motion at 256 px, training camera only (about a second to render)."""
    out = tmp_path_factory.mktemp("track_synth") / "seq"
    generate(
        SynthConfig(out=out, seed=3, num_frames=48, size=256, num_novel_views=0), body=body, progress=False
    )
    return load_ground_truth(out)


@pytest.fixture(scope="session")
def synth_512(tmp_path_factory, body):
    """24 frames at 512 px (the detector's accuracy is stated at this size)."""
    out = tmp_path_factory.mktemp("track_synth512") / "seq"
    generate(
        SynthConfig(out=out, seed=4, num_frames=24, size=512, num_novel_views=0), body=body, progress=False
    )
    return load_ground_truth(out)
