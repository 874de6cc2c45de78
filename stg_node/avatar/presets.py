"""The three presets users choose between: fast, balanced, quality.

Each is a complete :class:`TrainConfig`; they differ in Gaussian budget, iterations and the
colour model's size, not in what the method is (every preset is the full STG-Avatar: LBS +
spacetime terms + flow-guided densification + colour MLP). Measured time and quality of each,
on this project's reference CPU and on a GPU, are in docs/BENCHMARKS.md (tools/tradeoff.py).
"""

from __future__ import annotations

from stg_node.avatar.config import DensifyConfig, LossConfig, ModelConfig, TrainConfig

PRESETS = ("fast", "balanced", "quality")


def preset(name: str) -> TrainConfig:
    """The named preset (``fast``, ``balanced`` or ``quality``)."""
    if name == "fast":
        return TrainConfig(
            preset="fast",
            model=ModelConfig(num_gaussians=12_000, max_gaussians=30_000, feature_dim=12, mlp_width=48),
            loss=LossConfig(),
            densify=DensifyConfig(interval=150, flow_max_new=300),
            iterations=1500,
        )
    if name == "balanced":
        return TrainConfig(
            preset="balanced",
            model=ModelConfig(num_gaussians=20_000, max_gaussians=50_000),
            densify=DensifyConfig(),
            iterations=3000,
        )
    if name == "quality":
        return TrainConfig(
            preset="quality",
            model=ModelConfig(
                num_gaussians=30_000, max_gaussians=100_000, sh_degree=2, feature_dim=24, mlp_width=96
            ),
            densify=DensifyConfig(interval=200, flow_max_new=1000),
            iterations=6000,
            lr_pose=5e-5,
        )
    raise ValueError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
