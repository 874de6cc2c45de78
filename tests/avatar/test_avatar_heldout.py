"""A live trainer scored on held-out cameras (what the online trainer node reports at the end of the demo)."""

from __future__ import annotations

import numpy as np
import pytest
from avatar_helpers import small_config

from stg_node.avatar import evaluate_trainer
from stg_node.avatar.data_spec import DataSpec
from stg_node.avatar.evaluate import evaluate_split
from stg_node.avatar.renderer import AvatarRenderer
from stg_node.avatar.trainer import Trainer


def test_evaluate_trainer_matches_the_published_snapshot_on_the_held_out_cameras(tiny_frames, tiny_synth):
    trainer = Trainer(small_config(iterations=20, lr_pose=1e-3), seed=0)
    trainer.add_frames(tiny_frames)
    for _ in range(20):
        trainer.step()
    assert trainer.pose_deltas is not None and float(trainer.pose_deltas.detach().abs().max()) > 0
    live = evaluate_trainer(trainer, tiny_synth, lpips_net=None)
    assert live["split"] == "novel_view" and live["views"] == 2 * 3  # 2 held-out cameras x 3 frames

    # The same figures through another path: the published snapshot, the dataset opened by hand.
    renderer = AvatarRenderer.from_snapshot(trainer.snapshot())
    deltas = trainer.pose_deltas.detach().numpy()
    corrections = {frame: deltas[slot] for frame, slot in trainer.pose_slots.items()}
    dataset = DataSpec(str(tiny_synth), "synthetic", size=128).open("novel_view")
    report, _ = evaluate_split(
        renderer,
        dataset,
        split="novel_view",
        lpips_nets=(),
        pose_corrections=corrections,
        show_progress=False,
    )
    assert live["psnr"] == pytest.approx(report["psnr"], abs=1e-3)
    assert live["ssim"] == pytest.approx(report["ssim"], abs=1e-4)
    assert np.isfinite(live["psnr"]) and live["lpips"] is None


def test_evaluate_trainer_needs_a_model(tiny_synth):
    with pytest.raises(ValueError, match="no model"):
        evaluate_trainer(Trainer(small_config(iterations=1)), tiny_synth)
