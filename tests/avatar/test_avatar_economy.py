"""Model only what the scene requires, end to end: with the default settings the trainer switches the
non-rigid part off on a subject standing still (nothing moves that skinning misses) and keeps it on a
dancing one with garment dynamics, whose held-out frames it pays on (tools/bench_nonrigid.py's medium
scale: 256x256, 72 training frames, the fast preset's schedule x0.6 and budget x0.5).

The decision's mechanics (held-out frames, the evidence, the switch-off, forced choices, checkpoints)
are tested at reduced size in test_avatar_nonrigid.py; this is the slow end-to-end check."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))


@pytest.mark.slow
def test_the_still_subject_switches_the_non_rigid_part_off_and_the_dancing_one_keeps_it(tmp_path_factory):
    import bench_nonrigid
    import tradeoff

    from stg_node.avatar import Trainer, preset
    from stg_node.avatar.data_spec import DataSpec

    scale = bench_nonrigid.MEDIUM
    config = tradeoff.scaled(preset("fast"), scale)
    cache = tmp_path_factory.mktemp("economy")
    trainers = {}
    for motion in ("still", "dance"):
        folder = tradeoff.ensure_subject(cache, motion, scale)
        trainer = Trainer(config, seed=0)
        trainer.add_frames(DataSpec(str(folder), "synthetic", size=scale.size).open("train"))
        while trainer.iteration < config.iterations:
            trainer.step()
        assert trainer.skipped_steps == 0
        trainers[motion] = trainer
    still, dance = trainers["still"], trainers["dance"]
    assert still.decision.chose == "off" and "rigid model explains" in still.decision.why, still.decision
    assert still.stats()["active_motion_fraction"] == 0.0 and "motion_coef" not in still.model.table.names()
    assert dance.decision.chose == "on", dance.decision
    moving = {m: t.decision.evidence["moving_fraction"] for m, t in trainers.items()}
    assert moving["dance"] > 5 * moving["still"], moving
    assert dance.stats()["active_motion_fraction"] > 0.05
