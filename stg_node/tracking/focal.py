"""The focal length of an uncalibrated camera, from the person in the footage, and how sure that is.

Two cues. First the stride (stride.py: a walker's planted feet against the body's travel in depth);
when it does not pin the focal length (:func:`_stride_pins`), the perspective within the body:

A single view of a body of known proportions pins its distance only up to the focal length: a
longer lens with the person farther away gives the same image, except for perspective within
the body (the near parts of a body a metre or two away look larger than the far ones). With one
body shape for the whole sequence (bone lengths do not change), a wrong focal length makes the
fit explain that perspective with the wrong depth in every frame; the right one explains it
everywhere. The evidence is strongest when the person comes close to the camera and moves in
depth (a walk towards it, a turn); a person standing still far away carries almost none.

:func:`estimate_focal` re-fits a spread of the tracked frames' keypoints (stored by the first
tracking pass, so nothing is detected twice) for each focal length of a grid, with the shape
calibrated on those frames and then held, and sums each frame's robust fit cost. The estimate is
the minimum of that profile (a parabola through the best three grid points, in log focal
length); its spread comes from a block bootstrap over frames (contiguous blocks keep the
frames' correlation). It is **sure** when the minimum lies inside the grid, rests on at least
``MIN_FRAMES`` frames fitted at every focal length (a bootstrap of two or three blocks of
``BLOCK`` frames is tight whatever the truth: a 20-frame clip at 192 px read 28 degrees for 38,
"sure" before this rule), stands out (the
parabola rises by at least ``MIN_RISE`` of the minimum's cost at ``RISE_STEP`` either side of it)
and the 16-84 % bootstrap interval is within ``SURE_RELATIVE`` of the estimate; otherwise the
caller keeps its default field of view and says it is unsure, with the interval.

Why the rise, beside the bootstrap: a detector's errors are systematic (the same body part off the
same way in every frame), so a bootstrap over frames resamples the same bias and can be tight
around a wrong answer. Measured (docs/BENCHMARKS.md, "Real footage"): BlazePose keypoints of a
subject filmed with a 30 degree lens gave 37.6 degrees, bootstrap +-5 %, with a profile 0.6 %
deep; the true keypoints of a 90 degree subject gave 87.7 degrees with a profile 4.5 % deep.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import asdict, dataclass, field

import numpy as np

from stg_node.tracking.camera import from_fov
from stg_node.tracking.fitting import FitConfig, SmplFitter
from stg_node.tracking.stride import MIN_TRAVEL_M, MIN_WALK_SPEED, StrideEstimate, stride_focal
from stg_node.tracking.types import Keypoints

log = logging.getLogger(__name__)

GRID_FOV_DEG = (25.0, 31.0, 38.0, 46.0, 55.0, 65.0, 76.0, 88.0, 102.0)  # ~20 % steps in focal length
MAX_FRAMES = 36  # frames re-fitted per focal length (a spread of the confident ones)
MIN_FRAMES = 20
MIN_RISE = 0.02  # the profile's parabola must rise this much (relative) at RISE_STEP either side
RISE_STEP = math.log(1.2)  # a 20 % change of focal length
MIN_CONFIDENCE = 0.5
SURE_RELATIVE = 0.10  # the 16-84 % interval within +-10 % of the estimate
BOOTSTRAP = 200
BLOCK = 8  # frames per bootstrap block
MIN_STANCE_RUNS = 4  # the stride cue (stride.py) decides with at least this many stance runs


@dataclass(frozen=True)
class FocalObservation:
    """What the first tracking pass saw in one frame (full-resolution keypoints, undistorted)."""

    timestamp: float
    keypoints: Keypoints
    confidence: float


@dataclass(frozen=True)
class FocalEstimate:
    focal_px: float  # horizontal focal length of the estimate, pixels
    fov_deg: float  # the same as a horizontal field of view
    low_fov_deg: float  # 16-84 % bootstrap interval
    high_fov_deg: float
    sure: bool
    reason: str  # why (un)sure, in words
    frames: int  # frames the estimate used
    rise: float = 0.0  # relative rise of the profile at +-20 % focal length (MIN_RISE)
    profile: list[tuple[float, float]] = field(default_factory=list)  # (fov_deg, summed cost)
    cue: str = "perspective"  # what decided: "stride" (planted feet, stride.py) or the profile
    stride: dict | None = None  # the stride estimate (stride.StrideEstimate.as_dict), when tried

    def describe(self) -> str:
        verdict = "sure" if self.sure else "UNSURE"
        return (
            f"focal length from the footage: {self.fov_deg:.1f} deg horizontal field of view "
            f"(f = {self.focal_px:.0f} px; 68 % interval {self.low_fov_deg:.1f}-{self.high_fov_deg:.1f} deg, "
            f"{self.frames} frames): {verdict}, {self.reason}"
        )

    def to_json(self) -> str:
        return json.dumps({"method": "estimate", **asdict(self)})


def fov_of(focal_px: float, width: int) -> float:
    return math.degrees(2.0 * math.atan(0.5 * width / focal_px))


def _select(observations: list[FocalObservation], limit: int) -> list[int]:
    usable = [
        i for i, o in enumerate(observations) if o.keypoints is not None and o.confidence >= MIN_CONFIDENCE
    ]
    if len(usable) <= limit:
        return usable
    picks = np.linspace(0, len(usable) - 1, limit).round().astype(int)
    return [usable[p] for p in picks]


def _profile(observations, picks, body, layout, width, height, fovs, intrinsics_dist=None) -> np.ndarray:
    """(frames, len(fovs)) robust fit cost of each picked frame at each field of view (NaN: no fit,
    or a frame of the shape calibration)."""
    costs = np.full((len(picks), len(fovs)), np.nan)
    for column, fov in enumerate(fovs):
        camera = from_fov(width, height, fov)
        fitter = SmplFitter(
            body, layout, camera.K, FitConfig(iterations=4, calibration_frames=min(20, len(picks) // 3))
        )
        for row, index in enumerate(picks):
            obs = observations[index]
            result = fitter.fit(obs.keypoints, obs.timestamp)
            if result is None:
                continue
            was_calibrating = not fitter.calibrated
            fitter.add_calibration(result, max(obs.confidence, fitter.config.calibration_min_confidence))
            if not was_calibrating:
                costs[row, column] = result.cost
    return costs


def _rise(log_f: np.ndarray, profile: np.ndarray) -> float:
    """How much the profile's parabola (through the best three grid points) rises at ``RISE_STEP``
    from its vertex, relative to the minimum cost; 0 at the grid's edge or for a flat profile."""
    k = int(np.nanargmin(profile))
    if k == 0 or k == len(profile) - 1 or not profile[k] > 0:
        return 0.0
    (x0, x1, x2), (y0, y1, y2) = log_f[k - 1 : k + 2], profile[k - 1 : k + 2]
    a = ((y2 - y1) / (x2 - x1) - (y1 - y0) / (x1 - x0)) / (x2 - x0)  # second divided difference
    if not a > 0:
        return 0.0
    slope = (y1 - y0) / (x1 - x0) + a * (x1 - x0)  # the parabola's slope at x1
    lowest = y1 - slope**2 / (4 * a)  # its vertex's value
    return float(a * RISE_STEP**2 / lowest) if lowest > 0 else 0.0


def _minimum(log_f: np.ndarray, profile: np.ndarray) -> tuple[float, bool]:
    """(log focal length at the profile's minimum, whether it is inside the grid)."""
    k = int(np.nanargmin(profile))
    if k == 0 or k == len(profile) - 1:
        return float(log_f[k]), False
    x, y = log_f[k - 1 : k + 2], profile[k - 1 : k + 2]
    a, b, _ = np.polyfit(x, y, 2)
    if a <= 0:
        return float(log_f[k]), True
    return float(np.clip(-b / (2 * a), x[0], x[2])), True


def estimate_focal(
    observations: list[FocalObservation],
    body,
    layout,
    width: int,
    height: int,
    *,
    fovs: tuple[float, ...] = GRID_FOV_DEG,
    max_frames: int = MAX_FRAMES,
    seed: int = 0,
) -> FocalEstimate:
    """The focal length that best explains the sequence (module docstring), with its interval."""
    picks = _select(observations, max_frames)
    default = from_fov(width, height, 65.0).K[0, 0]
    if len(picks) < MIN_FRAMES:
        reason = f"only {len(picks)} confident frames (at least {MIN_FRAMES} needed)"
        return FocalEstimate(default, 65.0, min(fovs), max(fovs), False, reason, len(picks))
    fovs = tuple(sorted(fovs, reverse=True))  # increasing focal length
    focal = np.array([from_fov(width, height, f).K[0, 0] for f in fovs])
    ordered = sorted((o for o in observations if o.keypoints is not None), key=lambda o: o.timestamp)
    stride = stride_focal(ordered, body, layout, width, height, default, seed=seed)
    if _stride_pins(stride, focal):
        return _from_stride(stride, width, len(picks))
    log_f = np.log(focal)
    costs = _profile(observations, picks, body, layout, width, height, fovs)
    rows = np.all(np.isfinite(costs), axis=1)
    costs = costs[rows]
    if len(costs) < MIN_FRAMES // 2:
        reason = "too few frames fitted at every focal length"
        return FocalEstimate(default, 65.0, min(fovs), max(fovs), False, reason, len(costs))
    profile = costs.sum(axis=0)
    best, inside = _minimum(log_f, profile)
    rise = _rise(log_f, profile)
    rng = np.random.default_rng(seed)
    blocks = [np.arange(s, min(s + BLOCK, len(costs))) for s in range(0, len(costs), BLOCK)]
    draws = []
    for _ in range(BOOTSTRAP):
        chosen = np.concatenate([blocks[i] for i in rng.integers(0, len(blocks), len(blocks))])
        draws.append(_minimum(log_f, costs[chosen].sum(axis=0))[0])
    low, high = np.percentile(draws, [16, 84])
    f_best = float(math.exp(best))
    relative = max(math.exp(high) / f_best - 1.0, 1.0 - math.exp(low) / f_best)
    if not inside:
        sure, reason = (
            False,
            "the best fit lies at the edge of the range searched; the motion does not pin it",
        )
    elif len(costs) < MIN_FRAMES:
        sure, reason = (
            False,
            (
                f"only {len(costs)} frames fitted at every focal length (at least {MIN_FRAMES} needed: fewer "
                f"make fewer than {-(-MIN_FRAMES // BLOCK)} bootstrap blocks, whose interval says nothing)"
            ),
        )
    elif rise < MIN_RISE:
        sure, reason = (
            False,
            (
                f"the fit cost changes by only {100 * rise:.1f} % for a 20 % change of focal length (at "
                f"least {100 * MIN_RISE:g} % needed: the keypoints' own errors move a profile this flat; "
                "the person should walk towards or away from the camera, within a few metres of it)"
            ),
        )
    elif relative > SURE_RELATIVE:
        sure, reason = (
            False,
            (
                f"the interval spans +-{100 * relative:.0f} % (the person should move towards or away from "
                "the camera, and come within a few metres of it)"
            ),
        )
    else:
        sure, reason = (
            True,
            (f"the interval spans +-{100 * relative:.0f} %, the fit cost rises {100 * rise:.1f} % at +-20 %"),
        )
    if stride.runs:
        reason += f"; {_stride_words(stride, width)}"
    return FocalEstimate(
        focal_px=f_best,
        fov_deg=fov_of(f_best, width),
        low_fov_deg=fov_of(math.exp(high), width),
        high_fov_deg=fov_of(math.exp(low), width),
        sure=sure,
        reason=reason,
        frames=len(costs),
        rise=rise,
        profile=[(float(f), float(c)) for f, c in zip(fovs, profile, strict=True)],
        stride=stride.as_dict(),
    )


def _stride_pins(stride: StrideEstimate, grid_focal: np.ndarray) -> bool:
    """Whether the planted feet pin the focal length: a fixed point (the last fit's factor near 1),
    enough stance runs, travel in depth, legs at a walker's speed, a tight interval, inside the
    range searched."""
    return (
        stride.converged
        and stride.runs >= MIN_STANCE_RUNS
        and stride.travel_m >= MIN_TRAVEL_M
        and stride.speed_mps >= MIN_WALK_SPEED
        and stride.relative <= SURE_RELATIVE
        and grid_focal.min() <= stride.focal_px <= grid_focal.max()
    )


def _stride_words(stride: StrideEstimate, width: int) -> str:
    if not math.isfinite(stride.focal_px):
        return f"the planted feet do not say ({stride.runs} stance runs)"
    return (
        f"the planted feet say {fov_of(stride.focal_px, width):.1f} deg (+-{100 * stride.relative:.0f} %, "
        f"{stride.runs} stance runs, {stride.travel_m:.1f} m of travel in depth, legs at "
        f"{stride.speed_mps:.1f} m/s; sure needs {MIN_STANCE_RUNS} runs, {MIN_TRAVEL_M:g} m, "
        f"{MIN_WALK_SPEED:g} m/s and +-{100 * SURE_RELATIVE:.0f} %)"
    )


def _from_stride(stride: StrideEstimate, width: int, frames: int) -> FocalEstimate:
    reason = (
        f"a walk in depth with planted feet: {stride.runs} stance runs, {stride.travel_m:.1f} m of "
        f"travel in depth, interval +-{100 * stride.relative:.0f} %"
    )
    return FocalEstimate(
        focal_px=stride.focal_px,
        fov_deg=fov_of(stride.focal_px, width),
        low_fov_deg=fov_of(stride.high_px, width),
        high_fov_deg=fov_of(stride.low_px, width),
        sure=True,
        reason=reason,
        frames=stride.frames,
        cue="stride",
        stride=stride.as_dict(),
    )
