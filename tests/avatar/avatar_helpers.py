"""Helpers of the avatar tests (a module of its own: ``conftest`` names collide across test folders)."""

from __future__ import annotations


def small_config(**changes):
    """A fast configuration for tests (few Gaussians, short schedule)."""
    from stg_node.avatar.config import DensifyConfig, ModelConfig, TrainConfig

    config = TrainConfig(
        model=ModelConfig(num_gaussians=1500, max_gaussians=4000, feature_dim=8, mlp_width=32, pose_dim=4),
        densify=DensifyConfig(start_iter=20, interval=20, flow_max_new=200),
        iterations=60,
        checkpoint_every=20,
        log_every=5,
        crop_margin_px=8,
        sh_increase_every=20,
    )
    return config.replace(**changes) if changes else config
