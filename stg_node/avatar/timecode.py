"""The time code of a pose never seen in training (animation, the novel-pose split).

The spacetime terms are functions of time, but an animation brings poses, not times. Rule: a
new pose takes the time of the **nearest training frame in pose space**, where the distance
between two poses is the Frobenius distance between their 23 local joint rotation matrices
(the root orientation and the global Rh/Th are left out: turning or walking does not change
what the garment does relative to the body). The spacetime Gaussians then render the
non-rigid state that the most similar training pose had.

Stability: along an animation the nearest frame can flip back and forth between two distant
training times whose poses are about equally close, which would make time-local Gaussians
blink. :meth:`PoseTimeIndex.time_for` therefore keeps the previous choice unless another frame
is closer by a margin (hysteresis, ``HYSTERESIS`` of the current distance).

How far the rule reaches: the garment's state is a function of its history, not of the pose
alone, so an instant's non-rigid state carries over to a new pose only as it does to the next
frame, by continuity. A pose farther from every training pose than the largest step between
training poses adjacent in time (:meth:`PoseTimeIndex.reach`; steps of the motion only, not those
across skipped frames or the tracker's jumps: :func:`motion_steps`) has no such neighbour; from
``FADE_END`` times the reach on it renders the model's mean placement (no motion terms,
stg_node.avatar.renderer), and between the two the instant's non-rigid part fades out
(:meth:`PoseTimeIndex.trust`), so an animation that crosses the reach does not pop from one to the
other. Measured (issue 22, docs/BENCHMARKS.md round 10b): on the dancing subject the instant of a
pose 2.5 median frame-steps (1.8-1.9 reaches) away costs a held-out frame 1.2 dB against the mean
on one subject draw and gains 0.3 on the other; training frames rendered at the instant of their
nearest pose more than 5 frames away score -0.60 / -0.01 dB against the mean.

The index keeps at most ``capacity`` keys (a stream evicts the oldest half-stride by
reservoir-style thinning: every other key is dropped when full), so it stays small; a bounded
trainer keeps only the entries of the frames it still holds (:meth:`PoseTimeIndex.retain`).
"""

from __future__ import annotations

import numpy as np

from stg_node.body import lbs

HYSTERESIS = 0.15
# Where the nearest instant's non-rigid state has faded out entirely, in multiples of the reach. The
# fade is one (largest) training step wide: the garment goes from the instant's state to the mean over
# as much pose change as lay between two training frames, no faster than training saw it change; a
# narrower fade is a faster change, in the limit a pop. Cost measured (docs/BENCHMARKS.md, issue 22):
# the dancer's far held-out frame, 1.8-1.9 reaches out, keeps 1-10 % of its instant's state.
FADE_END = 2.0
# What the reach leaves out (motion_steps): a step over more than GAP_FACTOR median time steps, and
# the tracker's jumps and one-frame glitches, JUMP_FACTOR times the steps around them.
GAP_FACTOR = 1.5
JUMP_FACTOR = 3.0
STEP_KINDS = ("motion", "gap", "jump", "glitch")


def pose_key(poses: np.ndarray) -> np.ndarray:
    """(24, 3) or (B, 24, 3) axis-angle -> (B, 207) flattened local rotation matrices of joints 1..23."""
    import torch

    p = np.array(poses, dtype=np.float32).reshape(-1, 24, 3)  # a copy: bus arrays are read-only
    mats = lbs.axis_angle_to_matrix(torch.from_numpy(p[:, 1:]))
    return mats.reshape(p.shape[0], 23 * 9).numpy()


def motion_steps(keys: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Pose distances between consecutive ``keys`` (sorted by ``times``, at least two) that measure how
    far the pose moves from one frame to the next. Left out, where others remain:

    - a step across a gap in time (more than ``GAP_FACTOR`` times the median time step): frames the
      tracker skipped as untrusted, a stream's dropped messages; the pose travels several frames'
      worth over it;
    - a jump: a step ``JUMP_FACTOR`` times larger than the steps either side of it (and than the
      median step). The tracker's limb that flips and stays flipped for a while makes one; a real
      motion speeds up over frames, so its steps grow with their neighbours (the true motions of
      stg-synth's subjects: at most 1.08x the larger neighbour; BlazePose on the benchmark's dancer:
      two jumps of 5.5x and 12x, docs/BENCHMARKS.md "The reach on tracked poses");
    - the two steps in and out of a one-frame glitch: a pose ``JUMP_FACTOR`` times farther from
      both neighbours than they are from each other (and than the median step). A pose on the way
      from one neighbour to the other is at most as far from either as they are apart.

    One such step would otherwise set the reach of a whole clip (the largest step), and every new
    pose within it would render a training instant's non-rigid state however far it is from it.
    """
    steps, kinds = classify_steps(keys, times)
    motion = kinds == STEP_KINDS.index("motion")
    return steps[motion] if motion.any() else steps


def classify_steps(keys: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(steps, kinds): the pose distances between consecutive ``keys`` (sorted by ``times``) and each
    one's kind, an index into ``STEP_KINDS`` (:func:`motion_steps` says which is which)."""
    steps = np.linalg.norm(np.diff(keys, axis=0), axis=1)
    kinds = np.zeros(steps.shape[0], np.int64)
    dt = np.diff(np.asarray(times, np.float64))
    gap = dt > GAP_FACTOR * float(np.median(dt))  # the median time step's own steps are never a gap
    median = float(np.median(steps[~gap]))
    around = np.where(gap, 0.0, steps)  # a neighbour across a gap says nothing of the pace
    sides = np.maximum(np.r_[0.0, around[:-1]], np.r_[around[1:], 0.0])
    kinds[steps > JUMP_FACTOR * np.maximum(sides, median)] = STEP_KINDS.index("jump")
    if steps.shape[0] >= 2:
        across = np.linalg.norm(keys[2:] - keys[:-2], axis=1)  # frame i's neighbours, i = 1..n-2
        glitch = np.minimum(steps[:-1], steps[1:]) > JUMP_FACTOR * np.maximum(across, median)
        kinds[:-1][glitch] = STEP_KINDS.index("glitch")  # the step into the frame
        kinds[1:][glitch] = STEP_KINDS.index("glitch")  # and out of it
    kinds[gap] = STEP_KINDS.index("gap")
    return steps, kinds


class PoseTimeIndex:
    """Training poses and their normalised times; answers 'which time for this pose'."""

    def __init__(self, capacity: int = 2048):
        self.capacity = int(capacity)
        self.keys = np.zeros((0, 23 * 9), np.float32)
        self.times = np.zeros((0,), np.float32)
        self._reach: tuple[np.ndarray, float] | None = None  # (the keys it was measured on, the reach)
        self._last: tuple[np.ndarray, bytes, np.ndarray] | None = None  # (keys, pose bytes, distances)

    def __len__(self) -> int:
        return int(self.times.shape[0])

    def add(self, poses: np.ndarray, time_u: float) -> None:
        if len(self) >= self.capacity:
            self.keys = self.keys[::2].copy()
            self.times = self.times[::2].copy()
        self.keys = np.concatenate([self.keys, pose_key(poses)])
        self.times = np.concatenate([self.times, np.float32([time_u])])

    def retain(self, times: np.ndarray) -> None:
        """Keep the entries at ``times`` only (a bounded trainer: its held frames, so a stream's
        index stays as small as its frame store and never points at knots it has dropped)."""
        held = np.asarray(times, np.float64).reshape(-1)
        if len(self) == 0:
            return
        if held.size == 0:
            keep = np.zeros(len(self), bool)
        else:
            keep = np.isclose(self.times[:, None].astype(np.float64), held[None, :], atol=1e-6).any(axis=1)
        if not keep.all():
            self.keys = self.keys[keep].copy()
            self.times = self.times[keep].copy()

    def set(self, keys: np.ndarray, times: np.ndarray) -> None:
        self.keys = np.asarray(keys, np.float32).reshape(-1, 23 * 9)
        self.times = np.asarray(times, np.float32).reshape(-1)

    def reach(self) -> float:
        """The largest pose distance between training poses adjacent in time (0 with fewer than two):
        how far a pose may be from its nearest training pose and still count as a neighbour of an instant.
        Steps that are not the motion's are left out (:func:`motion_steps`): across frames the
        tracker skipped, and the tracker's jumps."""
        if len(self) < 2:
            return 0.0
        cached = self._reach
        if cached is not None and cached[0] is self.keys:  # every change assigns new key arrays
            return cached[1]
        order = np.argsort(self.times, kind="stable")
        value = float(motion_steps(self.keys[order], self.times[order]).max())
        self._reach = (self.keys, value)  # a render without a time asks once per frame: ~1.4 ms at 2k keys
        return value

    def distances(self, poses: np.ndarray) -> np.ndarray:
        """(K,) pose distance from ``poses`` to every key. A render without a time asks twice for the
        same pose (its time, then its trust): the last answer is kept until the pose or the keys change."""
        pose = np.ascontiguousarray(poses, dtype=np.float32)
        tag = pose.tobytes()
        last = self._last
        if last is not None and last[0] is self.keys and last[1] == tag:
            return last[2]
        dist = np.linalg.norm(self.keys - pose_key(pose), axis=1)
        self._last = (self.keys, tag, dist)
        return dist

    def within_reach(self, poses: np.ndarray) -> bool:
        """Whether a pose is as near a training pose as consecutive training poses are to each other
        (module docstring); an index of fewer than two poses has no measure of that and says yes."""
        return self.trust(poses) == 1.0

    def trust(self, poses: np.ndarray) -> float:
        """How far the nearest instant's non-rigid state stands for a pose: 1 within the reach, 0 at
        ``FADE_END`` times the reach and beyond, a smoothstep of the distance between (continuous with
        a continuous slope: the garment neither pops nor starts drifting abruptly). 1 for an index of
        fewer than two poses (no measure of a step)."""
        if len(self) < 2:
            return 1.0
        reach = self.reach()
        nearest = float(self.distances(poses).min())
        if nearest <= reach + 1e-6:
            return 1.0
        if reach <= 0.0:  # every training pose the same: no width to fade over
            return 0.0
        x = (nearest - reach) / ((FADE_END - 1.0) * reach)
        if x >= 1.0:
            return 0.0
        return 1.0 - x * x * (3.0 - 2.0 * x)

    def time_for(self, poses: np.ndarray, previous: int | None = None) -> tuple[float, int]:
        """(time, key index) for one pose; ``previous`` is the index chosen for the last frame."""
        if len(self) == 0:
            return 0.0, -1
        dist = self.distances(poses)
        best = int(dist.argmin())
        if previous is not None and 0 <= previous < len(self):
            if dist[previous] <= dist[best] * (1.0 + HYSTERESIS) + 1e-6:
                best = previous
        return float(self.times[best]), best
