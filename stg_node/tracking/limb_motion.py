"""How fast each joint turned between two frames, as far as the detector's 2D points can tell.

The fit's temporal term ties each joint to the last frame's within a plausible rotation speed.
One speed for every frame either holds a dancer's swinging arm back (too tight) or lets the
detector's jitter through on a slow walk (too loose). The evidence is in the points: a limb that
really moved carries its points far relative to the joint that turns it; jitter moves them a
few pixels in place. This module measures that per joint, so the fit can loosen the term only
where the limb moved (fitting.FitConfig.temporal_max_rad_per_s).

For each body joint k (SMPL joints 1..23) the *moved* targets are those whose body point rides on
k or a joint below it; the *anchor* is the target at joint k itself (or, failing that, at the
nearest joint above it; the centroid of all targets at the root). The evidence is the largest
image-plane turn of an anchor-to-moved-point segment between the frames, after taking the
detector's jitter off the segment end's displacement:

    turn_k = max_i max(0, |d_i - d_anchor| - jitter_px) / max(|x_i - x_anchor|, min_length_px)

(d: a point's displacement, x: its position in the previous frame). It is a lower bound of the
3D turn of the limb (a segment turning towards the camera shortens instead of turning) and an
upper bound of joint k's own share (joints below k move the same points).
"""

from __future__ import annotations

import numpy as np
import torch

NUM_BODY_JOINTS = 23


def target_carriers(model) -> np.ndarray:
    """(T,) for each of a BodyKeypoints model's points, the deepest joint whose rotation moves it:
    a joint point's parent (a joint's position turns with its parent), a surface landmark's most
    weighted joint, an offset point's carrier when deeper. 0 (the root) moves nothing here."""
    parents = model.parents.numpy()
    index = model.gather_index.numpy()
    landmark_carrier = model.landmark_weights.argmax(dim=1).numpy() if model.has_landmarks else None
    carriers = np.empty(len(index), dtype=np.int64)
    for i, g in enumerate(index):
        carriers[i] = parents[g] if g < 24 else landmark_carrier[g - 24]
        carriers[i] = max(carriers[i], 0)
    if model.has_offsets:
        offset = model.offset_carrier.numpy()
        for i in range(len(index)):
            if offset[i] > 0 and _is_ancestor(parents, carriers[i], offset[i]):
                carriers[i] = offset[i]
    return carriers


def _is_ancestor(parents: np.ndarray, joint: int, descendant: int) -> bool:
    """Whether ``joint`` is ``descendant`` or above it in the kinematic tree."""
    while descendant >= 0:
        if descendant == joint:
            return True
        descendant = int(parents[descendant]) if descendant > 0 else -1
    return False


class LimbMotion:
    """Per-joint evidence of a turn between two frames' keypoint targets (module docstring)."""

    def __init__(self, model):
        parents = model.parents.numpy()
        index = model.gather_index.numpy()
        carriers = target_carriers(model)
        count = len(index)
        self.moved = np.zeros((NUM_BODY_JOINTS, count), dtype=bool)
        self.anchor = np.zeros((NUM_BODY_JOINTS, count), dtype=bool)
        for k in range(1, NUM_BODY_JOINTS + 1):
            self.moved[k - 1] = [c > 0 and _is_ancestor(parents, k, int(c)) for c in carriers]
            joint = k
            while joint > 0 and not np.any(index == joint):
                joint = int(parents[joint])
            self.anchor[k - 1] = index == joint if joint > 0 else np.ones(count, dtype=bool)

    def turn(
        self, xy_before, ok_before, xy_after, ok_after, jitter_px: float, min_length_px: float
    ) -> np.ndarray:
        """(23,) radians each joint's limb turned in the image between the frames (0 where the
        points cannot tell: too few usable in both frames)."""
        xy_before, xy_after = _numpy(xy_before), _numpy(xy_after)
        ok = np.asarray(_numpy(ok_before), bool) & np.asarray(_numpy(ok_after), bool)
        moved_by = xy_after - xy_before
        turns = np.zeros(NUM_BODY_JOINTS)
        for k in range(NUM_BODY_JOINTS):
            anchor = self.anchor[k] & ok
            moved = self.moved[k] & ok & ~self.anchor[k]
            if not anchor.any() or not moved.any():
                continue
            base = xy_before[anchor].mean(axis=0)
            base_moved = moved_by[anchor].mean(axis=0)
            relative = np.linalg.norm(moved_by[moved] - base_moved, axis=1)
            length = np.maximum(np.linalg.norm(xy_before[moved] - base, axis=1), min_length_px)
            turns[k] = float(np.max(np.maximum(relative - jitter_px, 0.0) / length))
        return turns


def _numpy(value) -> np.ndarray:
    return value.detach().cpu().numpy() if isinstance(value, torch.Tensor) else np.asarray(value)
