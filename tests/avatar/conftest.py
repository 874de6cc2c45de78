"""Fixtures of the avatar tests: a tiny synthetic capture (stg-synth, 128x128) generated once per session."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def tiny_synth(tmp_path_factory):
    """12 frames at 128x128 (10 for training), 2 held-out cameras every 4th frame, no supersampling."""
    from pathlib import Path

    from stg_node.data.synth.generate import SynthConfig, generate

    out = Path(tmp_path_factory.mktemp("synth")) / "tiny"
    generate(
        SynthConfig(
            out=out, num_frames=12, size=128, num_novel_views=2, view_every=4, supersample=1, motion="dance"
        ),
        progress=False,
    )
    return out


@pytest.fixture(scope="session")
def tiny_frames(tiny_synth):
    from stg_node.avatar.data_spec import DataSpec
    from stg_node.avatar.frames import TrainFrame

    ds = DataSpec(str(tiny_synth), "synthetic", size=128).open("train")
    return [TrainFrame.from_sample(s) for s in ds]
