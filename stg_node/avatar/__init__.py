"""STG-Avatar: animatable Gaussian avatars from a monocular video (docs/AVATAR.md).

Public interface:

- :class:`Trainer` (add_frame / step / snapshot / save / load), driven by ``stg-train`` and by the
  online trainer node alike; :class:`TrainFrame` is what it learns from;
- :func:`preset` (``fast``, ``balanced``, ``quality``) -> :class:`TrainConfig`; :func:`for_footage`
  turns on what frames from a self-exposing camera need (the per-frame colour correction);
- :class:`AvatarRenderer` (``from_snapshot(msg)``, ``render(camera, smpl, time)``);
- :func:`evaluate_trainer`: a live trainer's model on a dataset's held-out cameras;
- snapshots and checkpoints: :mod:`stg_node.avatar.snapshot`.

Layout: gaussians (the parameter table), rigid (LBS), spacetime (STG terms), timecode (novel-pose
time rule), color (MLP / SH), model (composition), losses, densify (strategy), optim, frames,
trainer, snapshot / checkpoint, renderer, evaluate, animation, export, data_spec, run.
"""

from stg_node.avatar.config import DensifyConfig, LossConfig, ModelConfig, TrainConfig
from stg_node.avatar.evaluate import evaluate_trainer
from stg_node.avatar.exposure import for_footage
from stg_node.avatar.frames import TrainFrame
from stg_node.avatar.presets import PRESETS, preset
from stg_node.avatar.renderer import AvatarRenderer, RenderOutput
from stg_node.avatar.trainer import StepResult, Trainer

__all__ = [
    "PRESETS",
    "AvatarRenderer",
    "DensifyConfig",
    "LossConfig",
    "ModelConfig",
    "RenderOutput",
    "StepResult",
    "TrainConfig",
    "TrainFrame",
    "Trainer",
    "evaluate_trainer",
    "for_footage",
    "preset",
]
