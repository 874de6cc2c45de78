"""Procedural SMPL motion sequences for the synthetic benchmark: turn, walk, wave, dance, still, mixed.

Each motion is a set of smooth functions of time (sums of sinusoids whose amplitudes and
phases are drawn from a seeded generator and slowly modulated, so no two seconds repeat
exactly) that give per-joint Euler angles in SMPL's parent-relative frames, a root yaw
rate, a forward speed and a few root wobbles. Segments are cross-faded with a smoothstep
(angles and rates blend linearly, which keeps every angle inside its limit box), the yaw
and the ground-plane position are integrated from the blended rates, and the angles
are clamped to :mod:`joint_limits` before they become SMPL axis-angle vectors.

This is the project's one motion generator (tests and demos use it too). The sequence is a
:class:`~stg_node.body.params.SmplSequence`: SMPL poses in the body's own canonical frame (SMPL:
y up, facing +z), placed in a dataset's world by ``Rh``/``Th`` (docs/BODY.md, "Frames").

World frame (as in ZJU-MoCap): z up, floor at z = 0 once the generator places the feet.
At yaw 0 the subject faces -y, towards the training camera. Poses follow ZJU-MoCap's
convention: ``poses[:, 0] == 0`` and the global rotation lives in ``Rh``; ``Th`` here
holds only the ground-plane position (the generator adds the height that puts the
lowest vertex on the floor, which needs the body model).

Motions (``--motion``):
- ``turn``: standing and turning in place with slow arm raises and look-arounds (ZJU-MoCap style).
- ``walk``: a walking gait on a circle of 0.4-0.5 m radius (one circle for the whole sequence).
- ``wave``: standing, turning slowly, one arm raised and waving at about 2 Hz.
- ``dance``: fast (about 2 beats/s) bouncing, twisting, large arm swings, swaying.
- ``still``: standing nearly still: breathing, small slow head turns (a scene that needs almost
  no non-rigid modelling; the coverage rule below still turns it once, rigidly).
- ``crouch``: standing, squatting down and up again every few seconds, arms forward for balance.
- ``arms_up``: standing, raising both arms overhead and lowering them to the sides, stretching.
- ``reach``: standing, raising both arms far overhead with the elbows folded (hands behind the
  head, forearms against the upper arms) and lowering them again: joint angles at the ends of
  their ranges, far from what a clip of walking or turning shows (a held-out motion that
  extrapolates the shoulders and elbows).
- ``approach``: walks straight towards the training camera and away again (2 m each way,
  turning round at each end): the body's distance to the camera changes by 2 m, which is what
  a focal-length estimate from the footage needs (stg_node.tracking.focal).
- ``mixed`` (default): turn, walk, wave and dance in turn over the training range.

Held-out poses: the last ``novel_pose_start..`` frames use a fresh parameter draw of the
same motion (for ``mixed``: walking while waving, a combination never seen in training),
cross-faded in so the dynamics stay continuous; ``test_motion`` names other motions for them
instead (several play in equal parts of the held-out frames). Over the training range the
root yaw is adjusted by a constant rate so the body turns through at least one full
revolution: a fixed monocular camera then sees every side of the subject.

Held-out orientations: with ``train_yaw_deg`` the body's facing over the training frames is
confined to a window of that many degrees around facing the training camera (a slow sweep
through the window replaces the motion's own turning; walking becomes walking on the spot),
so the camera never sees the other sides. ``test_yaw_deg`` turns the held-out frames' window
by that many degrees (counter-clockwise seen from above): they show orientations never seen in
training. The turn is a cut between two clips (as a test clip taken minutes after the training
clip), recorded in ``cuts``; the generator restarts the garment's dynamics there.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from stg_node.body.params import SmplSequence
from stg_node.data.synth.gait import Feet
from stg_node.data.synth.joint_limits import (
    JOINT_INDEX,
    NUM_JOINTS,
    clamp_to_limits,
    euler_to_smpl_pose,
)
from stg_node.data.synth.rotations import axis_rotation, euler_zyx_to_matrix, matrix_to_axis_angle

MOTIONS = ("mixed", "turn", "walk", "wave", "dance", "still", "crouch", "arms_up", "reach", "approach")
DEFAULT_MOTION = "mixed"
CROSSFADE_SECONDS = 0.5
DEFAULT_NUM_BETAS = 10  # SMPL's usual shape space
# Steering onto the walking circle: heading error gain (1/s) and radial pull (dimensionless).
STEER_GAIN = 3.0
STEER_RADIAL_GAIN = 1.5
# Rotation from SMPL's frame (y up, facing +z) to the world (z up, facing -y): Rx(+90 deg).
SMPL_TO_WORLD = axis_rotation("x", np.pi / 2)
# Root wobble limits (pitch x, yaw y, roll z) in degrees, in the SMPL frame of the pelvis.
ROOT_WOBBLE_LIMITS_DEG = np.array([[-20.0, 20.0], [-30.0, 30.0], [-15.0, 15.0]])
UPPER_BODY_JOINTS = tuple(
    JOINT_INDEX[name]
    for name in (
        "neck",
        "head",
        "left_collar",
        "right_collar",
        "left_shoulder",
        "right_shoulder",
        "left_elbow",
        "right_elbow",
        "left_wrist",
        "right_wrist",
        "left_hand",
        "right_hand",
    )
)


@dataclass(frozen=True)
class MotionSegment:
    """A named stretch of the sequence: frames ``start`` (inclusive) to ``stop`` (exclusive)."""

    name: str
    start: int
    stop: int


@dataclass(frozen=True, eq=False)
class MotionSequence(SmplSequence):
    """A generated sequence: its SMPL parameters (the fields of :class:`SmplSequence`, in the
    ZJU-MoCap world below, before floor placement) and how it was made.

    ``poses`` (N, 24, 3) with ``poses[:, 0] == 0``; ``Rh`` (N, 3) the global rotation; ``Th``
    (N, 3) with z = 0 until the generator puts the feet on the floor; ``betas`` as given to
    :func:`make_motion`.
    """

    euler_deg: np.ndarray | None = None  # (N, 24, 3) float64 the clamped Euler angles the poses came from
    segments: tuple[MotionSegment, ...] = ()
    cuts: tuple[int, ...] = ()  # frames where a new clip starts (the root orientation jumps there)

    @property
    def num_frames(self) -> int:
        return len(self)


@dataclass
class _Drive:
    """What one motion primitive asks for at each instant (all arrays have N rows)."""

    euler: np.ndarray  # (N, 24, 3) degrees, before clamping
    yaw_rate: np.ndarray  # (N,) rad/s about world z
    speed: np.ndarray  # (N,) m/s along the facing direction
    root: np.ndarray  # (N, 3) degrees: pelvis pitch / yaw wobble / roll in the SMPL frame
    sway: np.ndarray  # (N, 2) metres: offset along the subject's left and forward axes
    walking: bool = False  # its yaw rate is the walking circle's curvature times the speed
    steered: bool = True  # while walking, steered onto the circle (False: the path is its own)
    stepping: np.ndarray | None = None  # (N,) how much the travel comes from the feet; None: walking's


@dataclass(frozen=True)
class _Style:
    """Drawn once per sequence, shared by every segment: turning sense and walking circle.

    Keeping them fixed means consecutive walking segments stay on one circle (same curvature)
    instead of drifting out of the cameras' view.
    """

    direction: float  # +1 counter-clockwise seen from above, -1 clockwise
    walk_radius: float  # metres


def _relaxed(n: int) -> np.ndarray:
    """Arms hanging slightly away from the body, elbows a little bent, everything else neutral."""
    euler = np.zeros((n, NUM_JOINTS, 3))
    _set_left(euler, "shoulder", np.array([0.0, 0.0, -70.0]))
    _set_left(euler, "elbow", np.array([0.0, -12.0, 0.0]))
    _mirror_pair(euler, "shoulder")
    _mirror_pair(euler, "elbow")
    return euler


def _set_left(euler: np.ndarray, part: str, value: np.ndarray) -> None:
    euler[:, JOINT_INDEX["left_" + part]] = value


def _mirror(angles: np.ndarray) -> np.ndarray:
    """Left-side angles -> the mirror-image right-side angles (x kept, y and z negated)."""
    out = np.array(angles, dtype=np.float64, copy=True)
    out[..., 1:] *= -1.0
    return out


def _mirror_pair(euler: np.ndarray, part: str) -> None:
    euler[:, JOINT_INDEX["right_" + part]] = _mirror(euler[:, JOINT_INDEX["left_" + part]])


def _modulation(t: np.ndarray, rng: np.random.Generator, depth: float = 0.25) -> np.ndarray:
    """A slow random amplitude modulation around 1 (keeps motions from being exactly periodic)."""
    freq = rng.uniform(0.05, 0.13)
    phase = rng.uniform(0, 2 * np.pi)
    return 1.0 + depth * np.sin(2 * np.pi * freq * t + phase)


def _zeros(t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    n = t.shape[0]
    return np.zeros(n), np.zeros(n), np.zeros((n, 3)), np.zeros((n, 2))


def _turn(t: np.ndarray, rng: np.random.Generator, style: _Style) -> _Drive:
    """Standing and turning in place (ZJU-MoCap's typical capture), arms rising and falling."""
    n = t.shape[0]
    euler = _relaxed(n)
    _, speed, root, sway = _zeros(t)
    yaw_rate = np.full(n, style.direction * 2 * np.pi / rng.uniform(7.0, 11.0))
    for side, sign in (("left", 1.0), ("right", -1.0)):
        f_raise, f_swing = rng.uniform(0.15, 0.35), rng.uniform(0.2, 0.4)
        p_raise, p_swing = rng.uniform(0, 2 * np.pi, size=2)
        raise_ = 0.5 - 0.5 * np.cos(2 * np.pi * f_raise * t + p_raise)
        left_equiv = np.stack(
            [
                20.0 * np.sin(2 * np.pi * 0.17 * t + p_swing),
                -15.0 * np.sin(2 * np.pi * f_swing * t + p_swing),
                -70.0 + 55.0 * raise_ * _modulation(t, rng, 0.2),
            ],
            axis=-1,
        )
        elbow = np.stack([np.zeros(n), -(12.0 + 40.0 * raise_), np.zeros(n)], axis=-1)
        if sign < 0:
            left_equiv, elbow = _mirror(left_equiv), _mirror(elbow)
        euler[:, JOINT_INDEX[f"{side}_shoulder"]] = left_equiv
        euler[:, JOINT_INDEX[f"{side}_elbow"]] = elbow
    look = rng.uniform(0, 2 * np.pi, size=3)
    euler[:, JOINT_INDEX["neck"]] = np.stack(
        [
            8.0 * np.sin(2 * np.pi * 0.21 * t + look[0]),
            25.0 * np.sin(2 * np.pi * 0.13 * t + look[1]),
            np.zeros(n),
        ],
        axis=-1,
    )
    euler[:, JOINT_INDEX["head"], 1] = 10.0 * np.sin(2 * np.pi * 0.17 * t + look[2])
    euler[:, JOINT_INDEX["spine2"], 1] = 8.0 * np.sin(2 * np.pi * 0.19 * t + look[0])
    shift = 4.0 * np.sin(2 * np.pi * rng.uniform(0.15, 0.3) * t + look[2])
    euler[:, JOINT_INDEX["left_hip"], 2] = shift
    euler[:, JOINT_INDEX["right_hip"], 2] = shift  # both legs lean the same way: a weight shift
    root[:, 2] = -0.5 * shift
    euler[:, JOINT_INDEX["left_knee"], 0] = 4.0 + 3.0 * np.maximum(0.0, np.sin(2 * np.pi * 0.3 * t))
    euler[:, JOINT_INDEX["right_knee"], 0] = 4.0 + 3.0 * np.maximum(0.0, -np.sin(2 * np.pi * 0.3 * t))
    return _Drive(euler, yaw_rate, speed, root, sway)


def _walk(t: np.ndarray, rng: np.random.Generator, style: _Style) -> _Drive:
    """A walking gait along the sequence's circle (0.4-0.5 m radius, so the subject stays in frame)."""
    n = t.shape[0]
    euler = _relaxed(n)
    _, _, root, sway = _zeros(t)
    stride_freq = rng.uniform(0.75, 0.95)  # gait cycles per second (two steps each)
    stride_length = rng.uniform(0.7, 0.9)  # metres per gait cycle
    speed = np.full(n, stride_length * stride_freq)
    yaw_rate = style.direction * speed / style.walk_radius
    phase0 = rng.uniform(0, 2 * np.pi)
    amp = _modulation(t, rng, 0.15)
    phase = 2 * np.pi * stride_freq * t + phase0

    def leg(ph: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        hip = -8.0 - 20.0 * amp * np.sin(ph)
        knee = 5.0 + 55.0 * amp * np.maximum(0.0, np.cos(ph + np.pi / 4)) ** 2
        ankle = 12.0 * np.sin(ph - np.pi / 3)
        return hip, knee, ankle

    for side, offset in (("left", 0.0), ("right", np.pi)):
        hip, knee, ankle = leg(phase + offset)
        euler[:, JOINT_INDEX[f"{side}_hip"], 0] = hip
        euler[:, JOINT_INDEX[f"{side}_knee"], 0] = knee
        euler[:, JOINT_INDEX[f"{side}_ankle"], 0] = ankle
        arm = np.stack(
            [np.zeros(n), 18.0 * amp * np.sin(phase + offset), np.full(n, -75.0)], axis=-1
        )  # arm swings opposite to the leg of its side
        elbow = np.stack([np.zeros(n), -(18.0 + 12.0 * (1 - np.sin(phase + offset)) / 2), np.zeros(n)], -1)
        if side == "right":
            arm, elbow = _mirror(arm), _mirror(elbow)
        euler[:, JOINT_INDEX[f"{side}_shoulder"]] = arm
        euler[:, JOINT_INDEX[f"{side}_elbow"]] = elbow
    euler[:, JOINT_INDEX["spine2"], 1] = 6.0 * np.sin(phase)
    euler[:, JOINT_INDEX["spine1"], 0] = 4.0
    root[:, 1] = -5.0 * np.sin(phase)
    root[:, 2] = 3.0 * np.sin(2 * phase)
    return _Drive(euler, yaw_rate, speed, root, sway, walking=True)


def _wave(t: np.ndarray, rng: np.random.Generator, style: _Style) -> _Drive:
    """Standing, turning slowly, one arm raised and waving; the arm comes down now and then."""
    n = t.shape[0]
    euler = _relaxed(n)
    speed, _, root, sway = _zeros(t)
    yaw_rate = np.full(n, style.direction * 2 * np.pi / rng.uniform(10.0, 14.0))
    side = "left" if rng.random() < 0.5 else "right"
    wave_freq = rng.uniform(1.6, 2.4)
    raise_period = rng.uniform(4.0, 6.0)
    phase = rng.uniform(0, 2 * np.pi)
    # Raised most of the time; a smooth dip lowers the arm once per period.
    envelope = np.clip(0.5 + 0.8 * np.cos(2 * np.pi * t / raise_period + phase), 0.0, 1.0)
    envelope = envelope * envelope * (3 - 2 * envelope)
    oscillation = np.sin(2 * np.pi * wave_freq * t)
    relaxed_shoulder = np.array([0.0, 0.0, -70.0])
    raised_shoulder = np.stack([np.full(n, -85.0), np.full(n, -20.0), 55.0 + 5.0 * oscillation], axis=-1)
    shoulder = relaxed_shoulder + envelope[:, None] * (raised_shoulder - relaxed_shoulder)
    elbow = np.stack([np.zeros(n), -(12.0 + envelope * (58.0 + 30.0 * oscillation)), np.zeros(n)], axis=-1)
    wrist = np.stack([np.zeros(n), np.zeros(n), 20.0 * envelope * oscillation], axis=-1)
    if side == "right":
        shoulder, elbow, wrist = _mirror(shoulder), _mirror(elbow), _mirror(wrist)
    euler[:, JOINT_INDEX[f"{side}_shoulder"]] = shoulder
    euler[:, JOINT_INDEX[f"{side}_elbow"]] = elbow
    euler[:, JOINT_INDEX[f"{side}_wrist"]] = wrist
    other = "right" if side == "left" else "left"
    sway_arm = 10.0 * np.sin(2 * np.pi * rng.uniform(0.2, 0.4) * t)
    other_shoulder = np.stack([np.zeros(n), sway_arm, np.full(n, -72.0)], axis=-1)
    euler[:, JOINT_INDEX[f"{other}_shoulder"]] = (
        other_shoulder if other == "left" else _mirror(other_shoulder)
    )
    euler[:, JOINT_INDEX["neck"], 1] = 15.0 * np.sin(2 * np.pi * 0.15 * t + phase)
    euler[:, JOINT_INDEX["head"], 0] = 5.0 * np.sin(2 * np.pi * 0.3 * t)
    euler[:, JOINT_INDEX["spine3"], 2] = (-6.0 if side == "left" else 6.0) * envelope
    return _Drive(euler, yaw_rate, speed, root, sway)


def _dance(t: np.ndarray, rng: np.random.Generator, style: _Style) -> _Drive:
    """A fast dance-like sequence: bouncing knees, twisting torso, large arm swings, side sway."""
    n = t.shape[0]
    euler = _relaxed(n)
    speed, _, root, sway = _zeros(t)
    beat = rng.uniform(1.8, 2.2)  # beats per second
    w = 2 * np.pi * beat
    amp = _modulation(t, rng, 0.2)
    phases = rng.uniform(0, 2 * np.pi, size=8)
    bounce = 0.5 - 0.5 * np.cos(w * t)
    spin = style.direction * 2 * np.pi * rng.uniform(0.06, 0.1)
    yaw_amp = np.deg2rad(rng.uniform(30.0, 45.0))
    yaw_freq = beat / 8
    yaw_rate = spin + yaw_amp * 2 * np.pi * yaw_freq * np.cos(2 * np.pi * yaw_freq * t + phases[0])
    for side, offset in (("left", 0.0), ("right", np.pi)):
        hip = -(12.0 + 14.0 * bounce) - 8.0 * np.sin(w / 2 * t + offset)
        knee = 18.0 + 28.0 * bounce + 6.0 * np.sin(w / 2 * t + offset)
        euler[:, JOINT_INDEX[f"{side}_hip"], 0] = hip
        euler[:, JOINT_INDEX[f"{side}_knee"], 0] = knee
        euler[:, JOINT_INDEX[f"{side}_ankle"], 0] = -(hip + knee) * 0.6
        euler[:, JOINT_INDEX[f"{side}_hip"], 2] = 8.0 + 4.0 * np.sin(w / 4 * t + offset)
        arm_phase = w / 2 * t + phases[1] + offset * rng.uniform(0.3, 1.0)
        shoulder = np.stack(
            [
                30.0 * np.sin(w / 4 * t + phases[2] + offset),
                -35.0 * amp * np.sin(arm_phase + phases[3]),
                10.0 + 55.0 * amp * np.sin(arm_phase),
            ],
            axis=-1,
        )
        elbow = np.stack(
            [np.zeros(n), -(45.0 + 40.0 * np.sin(w * t + phases[4] + offset)), np.zeros(n)], axis=-1
        )
        wrist = np.stack([np.zeros(n), np.zeros(n), 25.0 * np.sin(w * t + phases[5] + offset)], axis=-1)
        if side == "right":
            shoulder, elbow, wrist = _mirror(shoulder), _mirror(elbow), _mirror(wrist)
        euler[:, JOINT_INDEX[f"{side}_shoulder"]] = shoulder
        euler[:, JOINT_INDEX[f"{side}_elbow"]] = elbow
        euler[:, JOINT_INDEX[f"{side}_wrist"]] = wrist
        euler[:, JOINT_INDEX[f"{side}_collar"], 2] = (1 if side == "left" else -1) * 8.0 * bounce
    euler[:, JOINT_INDEX["spine1"], 0] = 8.0 + 6.0 * bounce
    euler[:, JOINT_INDEX["spine2"], 1] = 18.0 * amp * np.sin(w / 2 * t + phases[6])
    euler[:, JOINT_INDEX["spine3"], 2] = 8.0 * np.sin(w / 4 * t + phases[7])
    euler[:, JOINT_INDEX["neck"], 0] = 10.0 * bounce
    euler[:, JOINT_INDEX["head"], 1] = 20.0 * np.sin(w / 4 * t + phases[2])
    root[:, 0] = 6.0 * bounce
    root[:, 2] = 8.0 * np.sin(w / 4 * t + phases[7])
    sway[:, 0] = 0.12 * np.sin(w / 4 * t + phases[6])
    return _Drive(euler, yaw_rate, speed, root, sway)


def _still(t: np.ndarray, rng: np.random.Generator, style: _Style) -> _Drive:
    """Standing nearly still: breathing, small slow head turns, a faint weight shift; no turning of its own.

    What moves: the chest and shoulders with each breath (12-18 breaths a minute: about 1.5 deg of
    spine extension and 2 deg of collar lift), the head turning slowly left and right (up to about
    15 deg) and nodding a little, and a weight shift of about 1 deg at the hips. Arms hang relaxed.
    The sequence's coverage rule still turns the whole body through a revolution over the training
    range (a turntable, rigid: the root rotation ``Rh`` carries it, skinning explains it exactly).
    """
    n = t.shape[0]
    euler = _relaxed(n)
    yaw_rate, speed, root, sway = _zeros(t)
    breath_freq = rng.uniform(0.2, 0.3)
    phases = rng.uniform(0, 2 * np.pi, size=5)
    breath = 0.5 - 0.5 * np.cos(2 * np.pi * breath_freq * t + phases[0])  # 0 exhaled .. 1 inhaled
    breath = breath * _modulation(t, rng, 0.15)
    euler[:, JOINT_INDEX["spine2"], 0] = -0.8 * breath  # the chest lifts (extension) on the in-breath
    euler[:, JOINT_INDEX["spine3"], 0] = -0.7 * breath
    _set_left(euler, "collar", np.stack([np.zeros(n), np.zeros(n), 2.0 * breath], axis=-1))
    _mirror_pair(euler, "collar")
    turn_amp = rng.uniform(10.0, 15.0)
    euler[:, JOINT_INDEX["neck"], 1] = turn_amp * np.sin(2 * np.pi * rng.uniform(0.08, 0.14) * t + phases[1])
    euler[:, JOINT_INDEX["head"], 0] = 3.0 * np.sin(2 * np.pi * rng.uniform(0.1, 0.2) * t + phases[2])
    shift = 1.0 * np.sin(2 * np.pi * rng.uniform(0.05, 0.1) * t + phases[3])
    euler[:, JOINT_INDEX["left_hip"], 2] = shift
    euler[:, JOINT_INDEX["right_hip"], 2] = shift  # both legs lean the same way: a weight shift
    root[:, 2] = -0.5 * shift
    euler[:, JOINT_INDEX["left_knee"], 0] = 3.0
    euler[:, JOINT_INDEX["right_knee"], 0] = 3.0
    return _Drive(euler, yaw_rate, speed, root, sway)


def _crouch(t: np.ndarray, rng: np.random.Generator, style: _Style) -> _Drive:
    """Squatting down and up again (one squat every 2.5-3.5 s), arms forward for balance, turning slowly."""
    n = t.shape[0]
    euler = _relaxed(n)
    speed, _, root, sway = _zeros(t)
    yaw_rate = np.full(n, style.direction * 2 * np.pi / rng.uniform(11.0, 15.0))
    period = rng.uniform(2.5, 3.5)
    phase = rng.uniform(0, 2 * np.pi)
    depth = rng.uniform(0.7, 1.0)
    down = depth * (0.5 - 0.5 * np.cos(2 * np.pi * t / period + phase))  # 0 standing .. depth squatting
    down = down * down * (3 - 2 * down)  # lingers at the top and the bottom
    for side in ("left", "right"):
        hip = -(5.0 + 95.0 * down)
        knee = 4.0 + 120.0 * down
        euler[:, JOINT_INDEX[f"{side}_hip"], 0] = hip
        euler[:, JOINT_INDEX[f"{side}_knee"], 0] = knee
        euler[:, JOINT_INDEX[f"{side}_ankle"], 0] = -(hip + knee) * 0.8
        euler[:, JOINT_INDEX[f"{side}_hip"], 2] = (1.0 if side == "left" else -1.0) * 10.0 * down
    shoulder = np.stack([np.zeros(n), -75.0 * down, -70.0 + 55.0 * down], axis=-1)  # forward, for balance
    elbow = np.stack([np.zeros(n), -(12.0 + 20.0 * down), np.zeros(n)], axis=-1)
    euler[:, JOINT_INDEX["left_shoulder"]] = shoulder
    euler[:, JOINT_INDEX["left_elbow"]] = elbow
    _mirror_pair(euler, "shoulder")
    _mirror_pair(euler, "elbow")
    euler[:, JOINT_INDEX["spine1"], 0] = 25.0 * down  # the trunk leans forward over the feet
    euler[:, JOINT_INDEX["neck"], 0] = -10.0 * down  # eyes stay level
    euler[:, JOINT_INDEX["neck"], 1] = 15.0 * np.sin(2 * np.pi * 0.13 * t + phase)
    root[:, 0] = 15.0 * down
    return _Drive(euler, yaw_rate, speed, root, sway)


def _arms_up(t: np.ndarray, rng: np.random.Generator, style: _Style) -> _Drive:
    """Raising both arms overhead and lowering them to the sides (3-4.5 s a cycle), stretching sideways."""
    n = t.shape[0]
    euler = _relaxed(n)
    speed, _, root, sway = _zeros(t)
    yaw_rate = np.full(n, style.direction * 2 * np.pi / rng.uniform(11.0, 15.0))
    period = rng.uniform(3.0, 4.5)
    phases = rng.uniform(0, 2 * np.pi, size=3)
    lift = 0.5 - 0.5 * np.cos(2 * np.pi * t / period + phases[0])  # 0 arms down .. 1 overhead
    lag = 0.5 - 0.5 * np.cos(2 * np.pi * t / period + phases[0] - rng.uniform(0.2, 0.6))
    for side, level in (("left", lift), ("right", lag)):
        shoulder = np.stack(
            [15.0 * np.sin(2 * np.pi * t / period + phases[1]), -10.0 * level, -70.0 + 155.0 * level], axis=-1
        )
        elbow = np.stack([np.zeros(n), -(8.0 + 25.0 * (1.0 - level)), np.zeros(n)], axis=-1)
        if side == "right":
            shoulder, elbow = _mirror(shoulder), _mirror(elbow)
        euler[:, JOINT_INDEX[f"{side}_shoulder"]] = shoulder
        euler[:, JOINT_INDEX[f"{side}_elbow"]] = elbow
        euler[:, JOINT_INDEX[f"{side}_collar"], 2] = (1.0 if side == "left" else -1.0) * 15.0 * level
    stretch = np.sin(2 * np.pi * t / (2 * period) + phases[2])
    euler[:, JOINT_INDEX["spine2"], 2] = 10.0 * stretch * lift
    euler[:, JOINT_INDEX["spine3"], 2] = 8.0 * stretch * lift
    euler[:, JOINT_INDEX["spine3"], 0] = -8.0 * lift  # the chest opens as the arms go up
    euler[:, JOINT_INDEX["neck"], 0] = -15.0 * lift  # looking up at the hands
    return _Drive(euler, yaw_rate, speed, root, sway)


def _reach(t: np.ndarray, rng: np.random.Generator, style: _Style) -> _Drive:
    """Both arms raised far overhead with the elbows folded (hands behind the head), and down again.

    Each arm rises from hanging to 80 deg above the horizontal (a 150 deg swing of the shoulder) and
    its elbow folds to 120-145 deg on the way up, the second arm a little behind the first; the
    chest opens and the head tips back. A held-out motion for bodies trained on arms that hang or
    swing (turn, walk): the shoulders and elbows leave every training angle far behind.
    """
    n = t.shape[0]
    euler = _relaxed(n)
    speed, _, root, sway = _zeros(t)
    yaw_rate = np.full(n, style.direction * 2 * np.pi / rng.uniform(12.0, 16.0))
    period = rng.uniform(3.0, 4.0)
    phases = rng.uniform(0, 2 * np.pi, size=3)
    fold_depth = 120.0 + 25.0 * (0.5 + 0.5 * np.sin(2 * np.pi * t / (2.7 * period) + phases[1]))
    for side, delay in (("left", 0.0), ("right", rng.uniform(0.15, 0.45))):
        level = 0.5 - 0.5 * np.cos(2 * np.pi * t / period + phases[0] - delay)  # 0 down .. 1 overhead
        level = level * level * (3 - 2 * level)
        shoulder = np.stack([-20.0 * level, -25.0 * level, -70.0 + 150.0 * level], axis=-1)
        elbow = np.stack([np.zeros(n), -(12.0 + (fold_depth - 12.0) * level), np.zeros(n)], axis=-1)
        if side == "right":
            shoulder, elbow = _mirror(shoulder), _mirror(elbow)
        euler[:, JOINT_INDEX[f"{side}_shoulder"]] = shoulder
        euler[:, JOINT_INDEX[f"{side}_elbow"]] = elbow
        euler[:, JOINT_INDEX[f"{side}_collar"], 2] = (1.0 if side == "left" else -1.0) * 20.0 * level
    both = 0.5 - 0.5 * np.cos(2 * np.pi * t / period + phases[0])
    euler[:, JOINT_INDEX["spine3"], 0] = -12.0 * both  # the chest opens
    euler[:, JOINT_INDEX["neck"], 0] = -20.0 * both  # the head tips back
    euler[:, JOINT_INDEX["spine2"], 1] = 10.0 * np.sin(2 * np.pi * t / (2 * period) + phases[2])
    return _Drive(euler, yaw_rate, speed, root, sway)


def _walk_wave(t: np.ndarray, rng: np.random.Generator, style: _Style) -> _Drive:
    """Walking while waving: lower body and root from a walk, arms and head from a wave."""
    lower = _walk(t, rng, style)
    upper = _wave(t, rng, style)
    euler = lower.euler.copy()
    euler[:, list(UPPER_BODY_JOINTS)] = upper.euler[:, list(UPPER_BODY_JOINTS)]
    return _Drive(euler, lower.yaw_rate, lower.speed, lower.root, lower.sway, walking=True)


APPROACH_LENGTH_M = 2.0  # the straight walk towards the camera and back
APPROACH_SPEED_MPS = 0.7  # fixed (not drawn), so a held-out tail continues the same path
APPROACH_TURN_S = 1.2  # turning round at each end, stepping in place
APPROACH_RAMP_S = 0.3  # speed and turning rate fade in and out over this long


def _approach(t: np.ndarray, rng: np.random.Generator, style: _Style) -> _Drive:
    """Walking straight towards the training camera and away again, turning round at each end.

    The gait is the walk's; the path is a line through the origin along the subject's initial
    heading (facing the camera), from ``-L/2`` to ``+L/2``: walk half a leg towards the camera,
    turn round, walk a whole leg away, turn round (the same way: one revolution per cycle, so
    every side is seen), and so on. Speed and turning rate fade in and out (smoothstep). The path
    is a function of time alone, so a held-out tail (a fresh draw of the gait) stays on it."""
    gait = _walk(t, rng, style)
    speed_mps = APPROACH_SPEED_MPS
    leg = APPROACH_LENGTH_M / speed_mps
    period = 2.0 * (leg + APPROACH_TURN_S)
    phase = (t + 0.5 * leg) % period  # starts half-way along a leg, walking towards the camera
    in_leg = phase % (leg + APPROACH_TURN_S)  # time into the current leg-then-turn
    ramp = APPROACH_RAMP_S

    def window(x: np.ndarray, length: float) -> np.ndarray:
        up = np.clip(x / ramp, 0.0, 1.0)
        down = np.clip((length - x) / ramp, 0.0, 1.0)
        w = np.minimum(up, down)
        return w * w * (3 - 2 * w)

    walking = np.where(in_leg < leg, window(in_leg, leg), 0.0)
    turning = np.where(in_leg >= leg, window(in_leg - leg, APPROACH_TURN_S), 0.0)
    # The turn's rate integrates to pi over the (smoothstepped) turn.
    turn_area = APPROACH_TURN_S - ramp
    yaw_rate = style.direction * np.pi / turn_area * turning
    speed = speed_mps * walking * (leg / (leg - ramp))  # the ramps do not shorten the leg
    return _Drive(  # turning round at the ends is stepping on the spot: the feet pivot, the body stays
        gait.euler, yaw_rate, speed, gait.root, gait.sway, walking=True, steered=False, stepping=walking
    )


_PRIMITIVES = {
    "turn": _turn,
    "walk": _walk,
    "wave": _wave,
    "dance": _dance,
    "still": _still,
    "crouch": _crouch,
    "arms_up": _arms_up,
    "reach": _reach,
    "walk+wave": _walk_wave,
    "approach": _approach,
}


def _segment_plan(
    motion: str, num_frames: int, novel_pose_start: int, test_motion: tuple[str, ...] = ()
) -> list[tuple[str, int, int]]:
    """(primitive, start, stop) per segment: the training range first, then the held-out tail
    (``test_motion``: its motions in equal parts; default the training motion's, see module doc)."""
    train_end = min(max(novel_pose_start, 1), num_frames)
    plan: list[tuple[str, int, int]] = []
    if motion == "mixed":
        names = ("turn", "walk", "wave", "dance")
        bounds = np.linspace(0, train_end, len(names) + 1).round().astype(int)
        plan += [(name, int(a), int(b)) for name, a, b in zip(names, bounds[:-1], bounds[1:], strict=True)]
        tail = "walk+wave"
    else:
        plan.append((motion, 0, train_end))
        tail = motion
    if train_end < num_frames:
        if test_motion:
            bounds = np.linspace(train_end, num_frames, len(test_motion) + 1).round().astype(int)
            plan += [
                (name, int(a), int(b))
                for name, a, b in zip(test_motion, bounds[:-1], bounds[1:], strict=True)
            ]
        else:
            plan.append((tail, train_end, num_frames))
    return [seg for seg in plan if seg[2] > seg[1]]


def _blend_weights(frame_time: np.ndarray, starts: list[float], cut: float | None = None) -> np.ndarray:
    """(N, K) smoothstep cross-fade weights for K segments starting at ``starts`` (seconds); rows sum to 1.

    A segment starting at ``cut`` (seconds) starts there without a cross-fade (a new clip).
    """
    steps = [np.ones_like(frame_time)]
    for start in starts[1:]:
        if cut is not None and start == cut:
            steps.append((frame_time >= start).astype(np.float64))
            continue
        s = np.clip((frame_time - start) / CROSSFADE_SECONDS + 0.5, 0.0, 1.0)
        steps.append(s * s * (3 - 2 * s))
    steps.append(np.zeros_like(frame_time))
    return np.stack([steps[k] - steps[k + 1] for k in range(len(starts))], axis=-1)


def _integrate_root(
    yaw_rate: np.ndarray,
    speed: np.ndarray,
    walking: np.ndarray,
    style: _Style,
    dt: float,
    yaw0: float,
    feet: Feet | None = None,
    stepping: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Integrate yaw (N,) and ground position (N, 2) from the blended rates, frame by frame.

    ``walking`` (N,): how much each frame walks on the circle. While walking, a steering term
    turns the subject onto the sequence's circle around the origin (tangent to it, pulled
    radially back onto it), so every walking segment shares one circle and the subject never
    leaves the cameras' view. (A path of its own, as ``approach``'s, is not steered.)

    ``feet`` (the posed skeleton's ankles) with ``stepping`` (N,): a frame that steps travels by
    its stance foot (gait.py: the foot stays planted), blended with the speed by ``stepping``.
    """
    n = yaw_rate.shape[0]
    yaw = np.empty(n)
    ground = np.empty((n, 2))
    yaw[0], ground[0] = yaw0, 0.0
    radius = style.walk_radius
    for i in range(n - 1):
        heading = np.array([np.sin(yaw[i]), -np.cos(yaw[i])])  # facing -y at yaw 0
        steer = 0.0
        rho = float(np.hypot(*ground[i]))
        if walking[i] > 0 and rho > 1e-3:
            radial = ground[i] / rho
            tangent = style.direction * np.array([-radial[1], radial[0]])
            desired = tangent - STEER_RADIAL_GAIN * (rho - radius) / radius * radial
            error = np.arctan2(heading[0] * desired[1] - heading[1] * desired[0], heading @ desired)
            steer = walking[i] * STEER_GAIN * error
        yaw[i + 1] = yaw[i] + dt * (yaw_rate[i] + steer)
        ground[i + 1] = ground[i] + dt * speed[i] * heading
        if feet is not None and stepping[i] > 0:
            planted = feet.planted_step(i, yaw[i], yaw[i + 1])
            ground[i + 1] = ground[i] + stepping[i] * planted + (1.0 - stepping[i]) * dt * speed[i] * heading
    return yaw, ground


def make_motion(
    motion: str,
    num_frames: int,
    fps: float,
    rng: np.random.Generator,
    novel_pose_start: int | None = None,
    betas=None,
    *,
    test_motion: str | tuple[str, ...] | None = None,
    train_yaw_deg: float | None = None,
    test_yaw_deg: float | None = None,
    skeleton: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
) -> MotionSequence:
    """Generate ``num_frames`` frames of ``motion`` at ``fps``, reproducibly from ``rng``.

    ``novel_pose_start`` is the first held-out frame (default: all frames are training
    frames); frames from there on use a fresh draw of the motion's parameters, or
    ``test_motion`` (one motion or several, played in equal parts). ``train_yaw_deg`` and
    ``test_yaw_deg`` hold orientations out (module doc). ``betas`` (S,) is the body shape the
    sequence carries (default: ten zeros, the model's mean shape). ``skeleton(poses, Rh) -> (N, 24,
    3)`` poses the body's joints (SMPL axis-angle poses (N, 24, 3), rotations Rh (N, 3), no
    translation): with it the walking frames plant their feet (gait.py), without it the walks'
    feet slide (the travel is the drawn speed).
    """
    if motion not in MOTIONS:
        raise ValueError(f"unknown motion {motion!r}; choose one of {', '.join(MOTIONS)}")
    if num_frames < 1:
        raise ValueError(f"num_frames must be >= 1, got {num_frames}")
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    tests = held_out_motions(test_motion)
    if train_yaw_deg is not None and not 0.0 <= float(train_yaw_deg) < 360.0:
        raise ValueError(f"train_yaw_deg must be in [0, 360) degrees, got {train_yaw_deg}")
    if test_yaw_deg is not None and train_yaw_deg is None:
        raise ValueError(
            "test_yaw_deg needs train_yaw_deg: with the full turn in training no orientation is held out"
        )
    novel_pose_start = num_frames if novel_pose_start is None else int(novel_pose_start)
    frame_time = np.arange(num_frames) / fps
    plan = _segment_plan(motion, num_frames, novel_pose_start, tests)
    style = _Style(direction=float(rng.choice([-1.0, 1.0])), walk_radius=float(rng.uniform(0.4, 0.5)))
    drives = [_PRIMITIVES[name](frame_time, rng, style) for name, _, _ in plan]
    train_end = min(novel_pose_start, num_frames)
    cut = test_yaw_deg is not None and 0 < train_end < num_frames  # the held-out frames are another clip
    starts = [start / fps for _, start, _ in plan]
    weights = _blend_weights(frame_time, starts, train_end / fps if cut else None)

    def blend(field: str) -> np.ndarray:
        stacked = np.stack([getattr(d, field) for d in drives], axis=1)  # (N, K, ...)
        w = weights.reshape(weights.shape + (1,) * (stacked.ndim - 2))
        return (stacked * w).sum(axis=1)

    euler = clamp_to_limits(blend("euler"))
    euler[:, 0] = 0.0
    yaw_rate, speed = blend("yaw_rate"), blend("speed")
    root = np.clip(blend("root"), ROOT_WOBBLE_LIMITS_DEG[:, 0], ROOT_WOBBLE_LIMITS_DEG[:, 1])
    sway = blend("sway")

    dt = 1.0 / fps
    walking = weights @ np.array([float(d.walking) for d in drives])
    steered = weights @ np.array([float(d.walking and d.steered) for d in drives])
    yaw0 = rng.uniform(-0.3, 0.3)
    feet = None
    stepping = np.stack(
        [np.full(num_frames, float(d.walking)) if d.stepping is None else d.stepping for d in drives], axis=1
    )
    stepping = (weights * stepping).sum(axis=1)  # how much each frame's travel comes from its feet
    if skeleton is not None and train_yaw_deg is None and np.any(stepping > 0):
        unturned = SMPL_TO_WORLD @ euler_zyx_to_matrix(np.deg2rad(root))  # the pose's own lean, no yaw
        feet = Feet(skeleton(euler_to_smpl_pose(euler).astype(np.float32), matrix_to_axis_angle(unturned)))
    yaw, ground = _integrate_root(yaw_rate, speed, steered, style, dt, yaw0, feet, stepping)
    cuts: tuple[int, ...] = ()
    if train_yaw_deg is not None:
        # Held-out orientations: a sweep through the window replaces the motion's own turning,
        # and walking happens on the spot (a walking circle would turn the body all round).
        yaw = _confined_yaw(frame_time, train_end, float(train_yaw_deg), test_yaw_deg, rng)
        ground = np.zeros((num_frames, 2))
        cuts = (train_end,) if cut else ()
    elif train_end > 1:
        # Full coverage: over the training range the body turns through >= one whole revolution.
        # The extra turning goes to the standing frames (walking follows its circle).
        turned = yaw[train_end - 1] - yaw[0]
        target = style.direction * max(2 * np.pi, np.ceil(abs(turned) / (2 * np.pi)) * 2 * np.pi)
        standing = 1.0 - walking
        room = standing[: train_end - 1].sum() * dt
        if room > 1e-6 and abs(target) > abs(turned):
            yaw_rate = yaw_rate.copy()
            yaw_rate[:train_end] += standing[:train_end] * (target - turned) / room
            yaw, ground = _integrate_root(yaw_rate, speed, steered, style, dt, yaw0, feet, stepping)
    yaw_rot = axis_rotation("z", yaw)  # (N, 3, 3)
    forward = yaw_rot @ np.array([0.0, -1.0, 0.0])
    left = yaw_rot @ np.array([1.0, 0.0, 0.0])
    position = np.zeros((num_frames, 3))
    position[:, :2] = ground
    position += sway[:, :1] * left + sway[:, 1:] * forward

    rotation = yaw_rot @ SMPL_TO_WORLD @ euler_zyx_to_matrix(np.deg2rad(root))
    segments = tuple(MotionSegment(name, start, stop) for name, start, stop in plan)
    return MotionSequence(
        poses=euler_to_smpl_pose(euler).astype(np.float32),
        Rh=matrix_to_axis_angle(rotation).astype(np.float32),
        Th=position.astype(np.float32),
        betas=np.zeros(DEFAULT_NUM_BETAS, np.float32) if betas is None else betas,
        fps=float(fps),
        source=f"stg_node.data.synth.make_motion({motion!r})",
        euler_deg=euler,
        segments=segments,
        cuts=cuts,
    )


def held_out_motions(test_motion: str | tuple[str, ...] | list[str] | None) -> tuple[str, ...]:
    """The held-out frames' motions as a tuple of primitives: a name, a comma-separated list, or a
    sequence; ``mixed`` stands for its four parts; None or empty means the default (module doc)."""
    if test_motion is None:
        return ()
    names = test_motion.split(",") if isinstance(test_motion, str) else list(test_motion)
    out: list[str] = []
    for name in (n.strip() for n in names):
        if not name:
            continue
        if name not in MOTIONS:
            raise ValueError(f"unknown test motion {name!r}; choose from {', '.join(MOTIONS)}")
        out += ["turn", "walk", "wave", "dance"] if name == "mixed" else [name]
    return tuple(out)


def _confined_yaw(
    frame_time: np.ndarray, train_end: int, window_deg: float, test_yaw_deg: float | None, rng
) -> np.ndarray:
    """Yaw (N,) sweeping slowly through a window of ``window_deg`` centred on facing the camera
    (yaw 0) over the training frames, and centred on ``test_yaw_deg`` after them (when given).

    The sweep is a sine whose period fits in the training frames (so the training range covers
    the window) and is at most 8 s (a person looking about, not spinning).
    """
    half = np.radians(window_deg) / 2.0
    train_duration = frame_time[max(train_end - 1, 0)] - frame_time[0]
    period = min(rng.uniform(5.0, 8.0), max(train_duration, 1.0))
    phase = rng.uniform(0, 2 * np.pi)
    yaw = half * np.sin(2 * np.pi * frame_time / period + phase)
    if test_yaw_deg is not None:
        yaw[train_end:] += np.radians(float(test_yaw_deg))
    return yaw
