"""The focal length from a walker's planted feet: the body's travel in depth against its legs.

A camera of unknown focal length sees a body of known size (the calibrated shape) at a depth that
scales with the focal length: fitted with ``s`` times the true focal length, every frame's body
sits ``s`` times as deep, at the same place in the picture (its sideways position and its pose
unchanged, as long as the perspective within the body is small). A walker's stance foot stays
where it was put while the body passes over it, so over a stance the body's travel in depth must
equal the legs' own: with the pelvis at depth ``Z_t`` and the stance ankle ``d_t`` in front of or
behind it (a depth offset in metres: the detector's 3D points, scaled to the fitted body's leg
length; the fit's own stance-foot swing came out at 0.4 of the truth on true keypoints, damped by
its priors), ``s * Z_t + d_t`` is constant. Each stance run ``r`` (consecutive frames with the
same stance leg, lifted clear of the other, its ends left out) says, in closed form,

    s_r = - b_r(d) / b_r(Z)

with ``b_r`` the least-squares rate of change over the run; the sequence's answer is the median
of the ``s_r`` weighted by ``w_r b_r(Z)^2`` (``w_r`` the run's time spread: the least-squares
weight), so a run where the foot pivots in a turn does not pull it. Rates rather than values keep
the per-frame jitter of the depth (a few per cent of the image scale) from biasing the ratio.
Unlike the perspective within the body (focal.py's profile), this needs no near camera: a walk
towards or away from the camera at any distance has it, and a detector's systematic error in the
2D points cancels in a ratio of rates (it scales the travel and the body alike). What it needs:
the person walks in depth (a person standing still, or walking across the picture, moves no foot
in depth, and is left to the profile), and a true depth swing of the legs from the detector's 3D
points.

:func:`stride_focal` fits consecutive tracked frames at a trial focal length (the shape calibrated
on the first frames, then held), finds the stance runs, solves for ``s`` and bootstraps over runs;
further passes at the corrected focal length (a secant in log focal length) look for the fixed
point, since the fit's depth does not scale exactly in proportion. Measured (docs/BENCHMARKS.md,
"The focal length from planted feet"): on true keypoints one walk of five is pinned (+7 %), the
others do not settle or spread; BlazePose's 3D points flatten the legs' depth swing to about a
quarter, which the walker's-speed gate (focal.py) refuses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from stg_node.tracking.camera import from_fov
from stg_node.tracking.fitting import FitConfig, SmplFitter

PELVIS, LEFT_ANKLE, RIGHT_ANKLE = 0, 7, 8
MAX_FRAMES = 150  # consecutive frames fitted per pass (every k-th frame of a longer sequence)
MIN_RUN_FRAMES = 5  # a stance run this long at least
RUN_TRIM = 0.2  # of a run's frames left out at each end (_middle)
MIN_WALK_SPEED = 0.6  # m/s: the legs' speed a stepping walker has at least (slower: the 3D points are flat)
STANCE_MARGIN_M = 0.03  # the stance ankle at least this much below the other, along the body's up
MIN_RUNS = 3
MIN_TRAVEL_M = 0.5  # the pelvis's travel in depth, summed over the runs, for a sure answer
BOOTSTRAP = 200
PASSES = 3  # fits of the sequence at most (the scaling law first, then a secant in log focal length)
CONVERGED = 0.02  # stop when a pass's factor is within this of 1
MIN_CONFIDENCE = 0.5


@dataclass(frozen=True)
class StrideEstimate:
    focal_px: float  # the estimate; NaN without stance runs
    low_px: float  # 16-84 % bootstrap interval over stance runs
    high_px: float
    runs: int  # stance runs used
    travel_m: float  # the pelvis's travel in depth over those runs (at the estimate)
    frames: int  # frames fitted
    speed_mps: float = math.nan  # the legs' speed in depth over the stance runs (weighted median)
    converged: bool = False  # the last pass's factor within CONVERGED of 1 (a fixed point, not a jump)

    @property
    def relative(self) -> float:
        """Half-width of the interval relative to the estimate (inf when there is none)."""
        if not (math.isfinite(self.focal_px) and self.focal_px > 0):
            return math.inf
        return max(self.high_px / self.focal_px - 1.0, 1.0 - self.low_px / self.focal_px)

    def as_dict(self) -> dict:
        return {
            "focal_px": self.focal_px if math.isfinite(self.focal_px) else None,
            "low_px": self.low_px if math.isfinite(self.low_px) else None,
            "high_px": self.high_px if math.isfinite(self.high_px) else None,
            "runs": self.runs,
            "travel_m": round(self.travel_m, 3),
            "frames": self.frames,
            "speed_mps": round(self.speed_mps, 3) if math.isfinite(self.speed_mps) else None,
            "converged": self.converged,
        }


def fov_of(focal_px: float, width: int) -> float:
    return math.degrees(2.0 * math.atan(0.5 * width / focal_px))


def _rate(t: np.ndarray, y: np.ndarray) -> float:
    dt = t - t.mean()
    return float((dt * (y - y.mean())).sum() / (dt * dt).sum())


def stance_runs(times: np.ndarray, up_heights: np.ndarray, max_gap: float) -> list[tuple[np.ndarray, int]]:
    """(frame indices, stance leg 0/1) of each run of consecutive frames whose stance leg is clear:
    ``up_heights`` (N, 2) the ankles' heights along the body's up axis; frames further apart than
    ``max_gap`` seconds break a run."""
    lower = np.argmin(up_heights, axis=1)
    clear = np.abs(up_heights[:, 0] - up_heights[:, 1]) >= STANCE_MARGIN_M
    runs, current = [], []
    for i in range(len(times)):
        joins = (
            current
            and clear[i]
            and lower[i] == lower[current[-1]]
            and times[i] - times[current[-1]] <= max_gap
        )
        if clear[i] and (not current or joins):
            current.append(i)
            continue
        if len(current) >= MIN_RUN_FRAMES:
            runs.append((np.array(current), int(lower[current[0]])))
        current = [i] if clear[i] else []
    if len(current) >= MIN_RUN_FRAMES:
        runs.append((np.array(current), int(lower[current[0]])))
    return [(_middle(frames), leg) for frames, leg in runs]


def _middle(frames: list[int]) -> np.ndarray:
    """The run without ``RUN_TRIM`` of its frames at each end: where a stance starts and ends the
    foot is still landing or already lifting (on true keypoints the whole runs read the focal
    length 18 % short, the middles 8 %)."""
    cut = int(round(RUN_TRIM * len(frames)))
    return np.array(frames[cut : len(frames) - cut] if len(frames) - 2 * cut >= 3 else frames)


def weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    order = np.argsort(values)
    cumulative = np.cumsum(weights[order])
    if not cumulative[-1] > 0:
        return math.nan
    return float(values[order][np.searchsorted(cumulative, 0.5 * cumulative[-1])])


def planted_scale(times, pelvis_z, offsets, runs, rng=None, draws: int = 0):
    """(s, per-run rates (runs, 3): weight, pelvis rate, stance ankle's offset rate, bootstrap
    draws of s): the focal length's error factor that keeps the stance feet still (module doc).

    ``pelvis_z`` (N,) depth of the pelvis (camera frame), ``offsets`` (N, 2) depth of each ankle
    relative to it. Each run says ``-b(d) / b(Z)``; the answer is their median weighted by
    ``w b(Z)^2`` (the least-squares weight), robust to the runs where a foot pivots or slides (a
    turn on the spot) rather than stays planted."""
    rates = []
    for frames, leg in runs:
        t = times[frames]
        spread = float(((t - t.mean()) ** 2).sum())
        rates.append((spread, _rate(t, pelvis_z[frames]), _rate(t, offsets[frames, leg])))
    rates = np.array(rates, dtype=np.float64).reshape(-1, 3)

    def solve(rows: np.ndarray) -> float:
        w, bz, bd = rows.T
        moving = np.abs(bz) > 1e-9
        if not moving.any():
            return math.nan
        return weighted_median(-bd[moving] / bz[moving], (w * bz * bz)[moving])

    s = solve(rates) if len(rates) else math.nan
    samples = np.array([])
    if rng is not None and draws and len(rates) >= 2:
        samples = np.array([solve(rates[rng.integers(0, len(rates), len(rates))]) for _ in range(draws)])
    return s, rates, samples


def network_offsets(observations, layout) -> tuple[np.ndarray, np.ndarray]:
    """From the detector's 3D points (metres, root-relative, camera-aligned): each ankle's depth
    relative to the hips' midpoint (N, 2) and each leg's length hip-knee-ankle (N, 2); NaN where
    a frame has no 3D points."""
    offsets = np.full((len(observations), 2), np.nan)
    lengths = np.full((len(observations), 2), np.nan)
    root = list(layout.root_sources)
    for i, obs in enumerate(observations):
        world = obs.keypoints.world
        if world is None:
            continue
        hips = np.asarray(world, np.float64)[root].mean(axis=0)
        for leg, side in enumerate(("left", "right")):
            hip, knee, ankle = (
                np.asarray(world[layout.index(f"{side}_{p}")], np.float64) for p in ("hip", "knee", "ankle")
            )
            offsets[i, leg] = ankle[2] - hips[2]
            lengths[i, leg] = np.linalg.norm(knee - hip) + np.linalg.norm(ankle - knee)
    return offsets, lengths


def _fit_sequence(observations, body, layout, K):
    """Fit the observations in order at camera ``K``: (indices of the fitted observations, their
    times, joints (N, 24, 3) camera frame, the body's up axis (N, 3)); the shape is calibrated on
    the first frames, which are then refitted with it."""
    calibration = min(20, max(len(observations) // 4, 1))
    fitter = SmplFitter(body, layout, K, FitConfig(iterations=4, calibration_frames=calibration))
    for obs in observations[:calibration]:
        result = fitter.fit(obs.keypoints, obs.timestamp)
        if result is not None:
            fitter.add_calibration(result, max(obs.confidence, fitter.config.calibration_min_confidence))
    if not fitter.calibrated:
        return np.zeros(0, int), np.zeros(0), np.zeros((0, 24, 3)), np.zeros((0, 3))
    fitter.reset()  # the shape is held; the calibration frames are fitted again with it
    times, poses, Rh, Th, kept = [], [], [], [], []
    for index, obs in enumerate(observations):
        result = fitter.fit(obs.keypoints, obs.timestamp)
        if result is None:
            continue
        kept.append(index)
        times.append(obs.timestamp)
        poses.append(result.poses)
        Rh.append(result.Rh)
        Th.append(result.Th)
    if not times:
        return np.zeros(0, int), np.zeros(0), np.zeros((0, 24, 3)), np.zeros((0, 3))
    like = body.v_template
    with torch.no_grad():
        out = body(
            betas=torch.as_tensor(np.asarray(fitter.betas)[None], dtype=like.dtype),
            poses=torch.as_tensor(np.stack(poses).reshape(len(poses), 72), dtype=like.dtype),
            Rh=torch.as_tensor(np.stack(Rh), dtype=like.dtype),
            Th=torch.as_tensor(np.stack(Th), dtype=like.dtype),
        )
    joints = out.joints.double().numpy()
    rotations = out.bone_transforms[:, PELVIS, :3, :3].double().numpy()
    up = rotations[:, :, 1]  # SMPL's y axis (up) in the camera frame
    return np.asarray(kept), np.asarray(times), joints, up


def _leg_ratio(joints: np.ndarray, network_legs: np.ndarray) -> float:
    """The fitted body's leg length (hip-knee-ankle) over the network's skeleton's (medians)."""
    body_legs = [
        np.linalg.norm(joints[:, k] - joints[:, h], axis=1)
        + np.linalg.norm(joints[:, a] - joints[:, k], axis=1)
        for h, k, a in ((1, 4, LEFT_ANKLE), (2, 5, RIGHT_ANKLE))
    ]
    network = np.nanmedian(network_legs) if np.isfinite(network_legs).any() else math.nan
    return float(np.median(np.concatenate(body_legs)) / network) if network > 0 else math.nan


def stride_focal(observations, body, layout, width: int, height: int, focal_px: float, seed: int = 0):
    """The focal length that keeps a walker's stance feet still (module doc), starting from the
    trial ``focal_px``; ``observations``: focal.FocalObservation in time order."""
    usable = [o for o in observations if o.keypoints is not None and o.confidence >= MIN_CONFIDENCE]
    step = max(1, math.ceil(len(usable) / MAX_FRAMES))
    usable = usable[::step]
    net_offsets, net_legs = network_offsets(usable, layout)
    if len(usable) < 2 * MIN_RUN_FRAMES or np.isfinite(net_offsets[:, 0]).sum() < 2 * MIN_RUN_FRAMES:
        return StrideEstimate(math.nan, math.nan, math.nan, 0, 0.0, len(usable))
    frame_gap = float(np.median(np.diff([o.timestamp for o in usable])))
    rng = np.random.default_rng(seed)
    estimate = StrideEstimate(math.nan, math.nan, math.nan, 0, 0.0, len(usable))
    trial, previous = float(focal_px), None  # previous: (log focal, log s) of the last pass
    for _ in range(PASSES):
        K = from_fov(width, height, float(np.clip(fov_of(trial, width), 5.0, 160.0))).K
        kept, times, joints, up = _fit_sequence(usable, body, layout, K)
        offsets = net_offsets[kept] * _leg_ratio(joints, net_legs[kept])  # the network's legs, body-sized
        known = np.all(np.isfinite(offsets), axis=1)
        kept, times, joints, up, offsets = kept[known], times[known], joints[known], up[known], offsets[known]
        if len(times) < 2 * MIN_RUN_FRAMES:
            return estimate
        heights = np.einsum("nkc,nc->nk", joints[:, [LEFT_ANKLE, RIGHT_ANKLE]] - joints[:, None, PELVIS], up)
        runs = stance_runs(times, heights, 2.5 * frame_gap)
        s, rates, draws = planted_scale(times, joints[:, PELVIS, 2], offsets, runs, rng, BOOTSTRAP)
        if len(runs) < MIN_RUNS or not (math.isfinite(s) and s > 0):
            return StrideEstimate(math.nan, math.nan, math.nan, len(runs), 0.0, len(times))
        draws = draws[np.isfinite(draws) & (draws > 0)]
        low, high = np.percentile(draws, [16, 84]) if len(draws) else (math.nan, math.nan)
        durations = np.array([times[f[-1]] - times[f[0]] for f, _ in runs])
        travel = float((np.abs(rates[:, 1]) * durations).sum() * s)
        speed = weighted_median(np.abs(rates[:, 2]), rates[:, 0] * rates[:, 1] ** 2)
        converged = abs(s - 1.0) < CONVERGED
        estimate = StrideEstimate(
            trial * s, trial * low, trial * high, len(runs), travel, len(times), speed, converged
        )
        if converged:
            break
        here = (math.log(trial), math.log(s))
        step = here[1]  # the scaling law: the focal length that makes s = 1
        if previous is not None and abs(here[1] - previous[1]) > 1e-6:  # a secant through two passes
            slope = (here[1] - previous[1]) / (here[0] - previous[0])
            if slope < 0:  # s falls as the trial focal length grows, as it must
                step = -here[1] / slope
        previous = here
        trial = math.exp(here[0] + float(np.clip(step, -1.0, 1.0)))
    return estimate
