"""Model only what the scene requires: trained with the same preset, a subject standing still ends with
fewer Gaussians and far fewer active motion terms than a dancing one (reduced size: 96x96, 24 training
frames, the fast preset's schedule and budget scaled by tools/tradeoff.py's rules)."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))


def test_still_subject_ends_with_fewer_gaussians_and_far_fewer_motion_terms(tmp_path_factory):
    import tradeoff

    from stg_node.avatar import Trainer, preset
    from stg_node.avatar.data_spec import DataSpec

    scale = dataclasses.replace(tradeoff.QUICK, iteration_factor=0.1)  # 150 steps of the fast preset
    config = tradeoff.scaled(preset("fast"), scale)
    cache = tmp_path_factory.mktemp("economy")
    stats = {}
    for motion in ("still", "dance"):
        folder = tradeoff.ensure_subject(cache, motion, scale)
        trainer = Trainer(config, seed=0)
        trainer.add_frames(DataSpec(str(folder), "synthetic", size=scale.size).open("train"))
        for _ in range(config.iterations):
            trainer.step()
        assert trainer.skipped_steps == 0
        s = trainer.stats()
        stats[motion] = (s["gaussians"], round(s["active_motion_fraction"] * s["gaussians"]))
    (still_n, still_active), (dance_n, dance_active) = stats["still"], stats["dance"]
    assert still_n < dance_n, stats
    assert 4 * still_active < dance_active, stats
