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
- **Alignment to the person masks first** (:func:`align_to_masks`): before the avatar learns,
  every training frame's correction is fitted so the body's silhouette covers the tracker's
  person mask (limbs placed where the image shows them), many cheap steps per frame at a small
  size, with the same priors. A tracked limb 10 cm off would otherwise pull the avatar's
  Gaussians after it in every frame it is seen in.
- **How much to refine** (:func:`refinement_for`): ground-truth or motion-capture parameters
  (a ``stg-synth`` subject, ZJU-MoCap's fits) need only a light touch; a tracker's poses need a
  correction of several degrees in a few visits per frame, so ``stg-train --format video`` uses
  the ``tracked`` settings unless ``--set`` says otherwise.

Held-out frames are never refined: a novel pose is rendered with the pose it is given.
"""

from __future__ import annotations

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
    pose_align_rounds: int


REFINEMENTS = {
    # Ground truth / motion capture: keep today's light touch.
    "given": Refinement(lr_pose=1e-4, pose_refine=1e-3, pose_smooth=0.0, pose_align_rounds=0),
    # A monocular tracker's poses: first aligned to the person masks (align_to_masks), then
    # corrections of several degrees within the few visits a training frame gets (about 15 in a
    # fast run of 100 frames), kept smooth in time.
    "tracked": Refinement(lr_pose=2e-3, pose_refine=1e-4, pose_smooth=1e-3, pose_align_rounds=20),
}


def refinement_for(config, source: str):
    """``config`` with the pose-refinement settings for poses from ``source`` ('given' or 'tracked')."""
    if source not in REFINEMENTS:
        raise ValueError(f"pose source must be one of {', '.join(REFINEMENTS)}, got {source!r}")
    r = REFINEMENTS[source]
    return config.replace(
        **{"lr_pose": r.lr_pose, "loss.pose_refine": r.pose_refine, "loss.pose_smooth": r.pose_smooth}
    )


# --- aligning the training poses to the person masks, before the avatar learns ----------------------
ALIGN_MAX_SIDE = 128  # the silhouettes are compared at most this large (the crop, downscaled)


@dataclass
class AlignReport:
    """What :func:`align_to_masks` did: frames, rounds, mean |alpha - mask| before and after."""

    frames: int
    rounds: int
    error_before: float
    error_after: float
    seconds: float

    def as_dict(self) -> dict:
        return {
            "frames": self.frames,
            "rounds": self.rounds,
            "mask_error_before": self.error_before,
            "mask_error_after": self.error_after,
            "seconds": self.seconds,
        }


def _silhouette(trainer, stored, body) -> tuple[torch.Tensor, torch.Tensor]:
    """(rendered alpha, mask) of one stored frame at most ALIGN_MAX_SIDE pixels, posed by ``body``."""
    import torch.nn.functional as F

    from stg_node.avatar.model import Camera3, PosedGaussians, _normalise, quat_multiply, render
    from stg_node.avatar.rigid import skin

    model = trainer.model
    table = model.table
    x0, y0, w, h = stored.crop
    scale = min(1.0, ALIGN_MAX_SIDE / max(w, h))
    camera = Camera3.from_camera(stored.frame.camera, stored.crop, trainer.device)
    if scale < 1.0:
        K = camera.K.clone()
        K[:2] *= scale
        K[0, 2] = (camera.K[0, 2] + 0.5) * scale - 0.5
        K[1, 2] = (camera.K[1, 2] + 0.5) * scale - 0.5
        camera = Camera3(camera.viewmat, K, max(16, round(w * scale)), max(16, round(h * scale)))
    bones = model.bones(body)
    skinned = skin(table["means"], model.skin_weights().detach(), bones)
    quats = quat_multiply(skinned.quats, _normalise(table["quats"].detach()))
    posed = PosedGaussians(
        skinned.means,
        quats,
        table.scales().detach(),
        table.opacities().detach(),
        torch.zeros_like(skinned.means),
        None,
    )
    _, alpha, _ = render(posed, camera, background=0.0, backend=trainer.backend)
    mask = torch.from_numpy(stored.frame.mask[y0 : y0 + h, x0 : x0 + w] > 127).float().to(trainer.device)
    mask = F.interpolate(mask[None, None], size=(camera.height, camera.width), mode="area")[0, 0]
    return alpha[..., 0], mask


def align_to_masks(trainer, rounds: int, lr: float = 1e-2, seed: int = 0) -> AlignReport:
    """Correct every stored frame's pose (``trainer.pose_deltas``) so the body's silhouette covers the
    person mask, before the avatar is trained on them.

    The body is the freshly initialised avatar (Gaussians on the body surface: its silhouette is
    the body's), rendered as alpha only at most ALIGN_MAX_SIDE pixels in the frame's crop. Each
    round visits every frame once (in a seeded order) and takes one Adam step on its correction
    for ``|alpha - mask|``, plus the corrections' size (``loss.pose_refine``) and the refined
    trajectory's smoothness (``loss.pose_smooth``, :class:`PoseTrack`): the silhouette moves the
    limbs that stick out of it, the priors keep the rest where the tracker put it. The avatar
    itself is not changed. Frames without a mask are left alone."""
    import time

    import numpy as np

    started = time.perf_counter()
    slots = trainer.pose_slots
    frames = [s for s in trainer.store.frames if s.frame.mask is not None and s.frame.index in slots]
    if trainer.model is None or trainer.pose_deltas is None or not frames or rounds <= 0:
        return AlignReport(len(frames), 0, float("nan"), float("nan"), 0.0)
    deltas = trainer.pose_deltas
    optimizer = torch.optim.Adam([deltas], lr=lr)
    config = trainer.config.loss
    rng = np.random.default_rng(seed)

    def error_of(stored) -> float:
        with torch.no_grad():
            alpha, mask = _silhouette(trainer, stored, trainer.body_state(stored.frame))
            return float((alpha - mask).abs().mean())

    before = float(np.mean([error_of(s) for s in frames]))
    for _ in range(rounds):
        for k in rng.permutation(len(frames)):
            stored = frames[k]
            optimizer.zero_grad()
            alpha, mask = _silhouette(trainer, stored, trainer.body_state(stored.frame))
            slot = trainer.pose_slots[stored.frame.index]
            loss = (alpha - mask).abs().mean() + config.pose_refine * deltas[slot].pow(2).sum()
            smooth = trainer.pose_track.smoothness(deltas, trainer.pose_slots, stored.frame.index)
            if smooth is not None and config.pose_smooth > 0:
                loss = loss + config.pose_smooth * smooth
            if not bool(torch.isfinite(loss)):
                continue
            loss.backward()
            if deltas.grad is not None and bool(torch.isfinite(deltas.grad).all()):
                optimizer.step()
    after = float(np.mean([error_of(s) for s in frames]))
    return AlignReport(len(frames), rounds, before, after, time.perf_counter() - started)
