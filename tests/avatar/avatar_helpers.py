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


def held_out_psnr(trainer, synth_folder, size: int = 128) -> float:
    """Mean PSNR (dB, 8-bit renders against the masked truth) of ``trainer``'s model on the
    held-out cameras of an stg-synth folder."""
    import math

    import numpy as np

    from stg_node.avatar.data_spec import DataSpec
    from stg_node.avatar.renderer import AvatarRenderer

    views = DataSpec(str(synth_folder), "synthetic", size=size).open("novel_view")
    renderer = AvatarRenderer(trainer.model)
    scores = []
    for sample in views:
        truth = np.where(sample.mask[..., None] > 127, sample.image, 0).astype(np.float64)
        image = renderer.render(sample.camera, sample.smpl, sample.time).image.astype(np.float64)
        mse = float(np.mean((image - truth) ** 2)) / 255.0**2
        scores.append(-10 * math.log10(max(mse, 1e-12)))
    return float(np.mean(scores))


def trained_held_out_psnr(frames, synth_folder, config, seed: int = 0) -> float:
    """Held-out PSNR of a model trained on ``frames`` with ``config`` for its whole schedule (the
    same-result checks of the training economies: one call per variant, same seed)."""
    from stg_node.avatar.trainer import Trainer

    trainer = Trainer(config, seed=seed)
    trainer.add_frames(frames)
    for _ in range(config.iterations):
        assert not trainer.step().skipped
    return held_out_psnr(trainer, synth_folder)


def density_step_inputs(iteration: int):
    """What a density step with no flow this step reads from the trainer (densify.step_post_backward)."""
    from types import SimpleNamespace

    import torch

    return SimpleNamespace(
        iteration=iteration,
        flow=None,
        grow_in_time=True,
        motion_threshold_px=1.0,
        time_range=(0.0, 1.0),
        generator=torch.Generator().manual_seed(0),
        rendered_flow=None,
    )


def spy_normal_signs(monkeypatch) -> list[bool]:
    """The ``outward`` flag of every shading-normals call from now on (the normal sign a step or a
    render used), while the real function still computes them."""
    from stg_node.avatar import model as model_module

    seen = []
    real = model_module.gaussian_normals

    def spy(quats, scales, means, camera_center, outward=False):
        seen.append(outward)
        return real(quats, scales, means, camera_center, outward)

    monkeypatch.setattr(model_module, "gaussian_normals", spy)
    return seen
