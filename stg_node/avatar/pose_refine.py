"""Refining the training poses with the avatar: smooth in time, and how strongly, by where they came from.

A tracked pose is off by some degrees per joint and a few centimetres per frame, and differently
in every frame: an avatar trained on such poses blurs (each frame pulls its Gaussians elsewhere)
and misplaces limbs in views the training camera never saw. The trainer learns a correction of
each training frame's pose (``Trainer.pose_deltas``: 72 joint-rotation values, the root
included, and 3 for the translation: the frame's global alignment) from the image. This module
adds what a per-frame correction alone lacks:

- **Temporal smoothness of the refined poses** (:class:`PoseTrack`): the second difference in
  time of each refined trajectory (``tracked + correction`` at frames ``i-1, i, i+1``), in units
  of what a body plausibly does in one frame (``ROTATION_SIGMA_RAD`` per joint,
  ``TRANSLATION_SIGMA_M`` for the root). A step then corrects three frames, not one, and frame
  jitter that no image supports is removed. Frames whose neighbours were never seen (a stream
  with gaps, or the first and last frame) are left to the per-frame terms.
- **How much to refine** (:func:`refinement_for`): ground-truth or motion-capture parameters
  (a ``stg-synth`` subject, ZJU-MoCap's fits) need only a light touch; a tracker's poses need a
  correction of several degrees in a few visits per frame, so ``stg-train --format video`` uses
  the ``tracked`` settings unless ``--set`` says otherwise.

- **Only the frames a step saw move** (:func:`hold_unseen_rows`): the corrections are one tensor
  in the trainer's dense Adam, whose moments keep moving every row for dozens of steps after it
  had a gradient, and whose tiny epsilon turns the weak whole-table regulariser into a full-size
  step for every row at every step. Each frame's correction would then random-walk by about the
  learning rate per step whether or not its image was seen: at the tracked setting's rate this
  cost 4 dB of novel-view PSNR with perfect poses (docs/BENCHMARKS.md "Real footage"). A step
  now moves the rows of the frame it rendered (and of its two neighbours when the smoothness
  term tied them in); the others stay put, as in a lazy (sparse) Adam.

Held-out frames are never refined: a novel pose is rendered with the pose it is given.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

ROTATION_SIGMA_RAD = 0.05  # second difference of a joint angle in one frame that costs one unit
TRANSLATION_SIGMA_M = 0.01  # ... of the root translation


class PoseTrack:
    """The tracked poses (and translations) of the training frames, to score refined trajectories."""

    def __init__(self):
        self.raw: dict[int, torch.Tensor] = {}  # frame index -> (75,) tracked poses (72) and Th (3)

    def add(self, index: int, smpl, device) -> None:
        values = torch.cat(
            [
                torch.as_tensor(smpl.poses, dtype=torch.float32).reshape(72),
                torch.as_tensor(smpl.Th, dtype=torch.float32).reshape(3),
            ]
        )
        self.raw[int(index)] = values.to(device)

    def retain(self, frames) -> None:
        """Keep the tracked poses of ``frames``, of their neighbours (the second difference of a
        held frame needs them) and the newest (the next frame's neighbour): a bounded trainer's
        track stays as long as its store."""
        newest = max(self.raw, default=None)
        self.raw = {
            f: v
            for f, v in self.raw.items()
            if f in frames or f - 1 in frames or f + 1 in frames or f == newest
        }

    def smoothness(self, deltas: torch.Tensor, slots: dict[int, int], index: int) -> torch.Tensor | None:
        """Mean squared, unit-scaled second difference of the refined trajectory around frame
        ``index``; None when a neighbour is missing."""
        frames = (index - 1, index, index + 1)
        if any(f not in self.raw or f not in slots for f in frames):
            return None
        refined = torch.stack([self.raw[f] + deltas[slots[f]] for f in frames])  # (3, 75)
        second = refined[0] - 2.0 * refined[1] + refined[2]
        scale = torch.full_like(second, 1.0 / ROTATION_SIGMA_RAD)
        scale[72:] = 1.0 / TRANSLATION_SIGMA_M
        return ((second * scale) ** 2).mean()


@dataclass(frozen=True)
class Refinement:
    """How strongly the training poses are refined: the learning rate of the corrections, the
    weight keeping them small, and the weight of the temporal smoothness."""

    lr_pose: float
    pose_refine: float
    pose_smooth: float


REFINEMENTS = {
    # Ground truth / motion capture: keep today's light touch.
    "given": Refinement(lr_pose=1e-4, pose_refine=1e-3, pose_smooth=0.0),
    # A monocular tracker's poses: corrections of several degrees within the few visits a
    # training frame gets (about 15 in a fast run of 100 frames), kept smooth in time.
    "tracked": Refinement(lr_pose=2e-3, pose_refine=1e-4, pose_smooth=1e-3),
}


def refinement_for(config, source: str):
    """``config`` with the pose-refinement settings for poses from ``source`` ('given' or 'tracked')."""
    if source not in REFINEMENTS:
        raise ValueError(f"pose source must be one of {', '.join(REFINEMENTS)}, got {source!r}")
    r = REFINEMENTS[source]
    return config.replace(
        **{"lr_pose": r.lr_pose, "loss.pose_refine": r.pose_refine, "loss.pose_smooth": r.pose_smooth}
    )


def pose_warmup_factor(progress: float, warmup: float, boost: float) -> float:
    """The pose corrections' learning-rate factor at ``progress`` (0..1 of the run): ``boost`` for
    the first ``warmup`` fraction, easing back to 1 (cosine) over the next ``warmup`` fraction.
    Poses first, while the avatar is still coarse: the mask and the blurred appearance then say
    where a limb is, and a pose settled early is one the avatar's detail is learnt on."""
    if boost == 1.0 or warmup <= 0.0 or progress >= 2.0 * warmup:
        return 1.0
    if progress <= warmup:
        return boost
    ease = 0.5 * (1.0 + math.cos(math.pi * (progress - warmup) / warmup))  # 1 -> 0
    return 1.0 + (boost - 1.0) * ease


def touched_slots(slots: dict[int, int], index: int, smoothed: bool) -> list[int]:
    """The correction rows a step on frame ``index`` has a real gradient for: the frame's, and its
    neighbours' when the smoothness term was in the loss."""
    frames = (index - 1, index, index + 1) if smoothed else (index,)
    return [slots[f] for f in frames if f in slots]


def hold_unseen_rows(deltas: torch.Tensor, touched: list[int]):
    """Before an optimiser step: a function that, called after it, puts every row of ``deltas`` but
    ``touched`` back where it was (module docstring)."""
    keep = torch.ones(deltas.shape[0], dtype=torch.bool, device=deltas.device)
    keep[torch.as_tensor(touched, dtype=torch.long, device=deltas.device)] = False
    before = deltas.detach()[keep].clone()

    def restore() -> None:
        with torch.no_grad():
            deltas[keep] = before

    return restore
