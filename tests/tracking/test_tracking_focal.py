"""The focal length from the footage (stg_node.tracking.focal) against synthetic truth.

Keypoints are the true body points of stg-synth subjects projected by their true camera (plus
pixel noise) with their true 3D directions, so what is tested is the estimator, not the detector:
a subject walking towards the camera pins the focal length, one standing still far away does not
and must be called unsure."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from trackhelpers import load_ground_truth

from stg_node.data.synth import SynthConfig, generate
from stg_node.tracking import focal, stride
from stg_node.tracking.body_points import BodyKeypoints
from stg_node.tracking.focal import RISE_STEP, FocalObservation, _minimum, _rise, estimate_focal, fov_of
from stg_node.tracking.layouts import get_layout
from stg_node.tracking.types import Keypoints


def observations(body, truth, noise_px: float = 0.5, every: int = 1, seed: int = 0) -> list[FocalObservation]:
    layout = get_layout("blazepose33")
    model = BodyKeypoints(body, [t.point for t in layout.targets]).double()
    rng = np.random.default_rng(seed)
    out = []
    for i in range(0, len(truth), every):
        with torch.no_grad():
            points = model(
                torch.as_tensor(truth.betas)[None],
                torch.as_tensor(truth.poses[i, 1:])[None],
                torch.as_tensor(truth.Rh[i])[None],
                torch.as_tensor(truth.Th[i])[None],
            )[0].numpy()
        camera = points @ truth.R.T + truth.t
        uv = camera @ truth.K.T
        uv = uv[:, :2] / uv[:, 2:]
        xy, score, world = np.zeros((33, 2)), np.zeros(33), np.zeros((33, 3))
        for k, target in enumerate(layout.targets):
            for source in target.sources:
                xy[source], score[source], world[source] = uv[k], 1.0, camera[k] - camera.mean(axis=0)
        xy += rng.normal(0.0, noise_px, xy.shape)
        kp = Keypoints(
            "blazepose33", xy.astype(np.float32), score.astype(np.float32), world.astype(np.float32)
        )
        out.append(FocalObservation(i / 30.0, kp, 1.0))
    return out


def subject(tmp_path_factory, name: str, **config):
    out = tmp_path_factory.mktemp("focal") / name
    generate(SynthConfig(out=out, size=256, num_novel_views=0, supersample=1, **config), progress=False)
    return load_ground_truth(out)


def true_fov(truth) -> float:
    return fov_of(truth.K[0, 0], truth.size)


def test_the_profile_minimum_is_the_parabolas_vertex():
    log_f = np.log([200.0, 240.0, 288.0, 346.0, 415.0])
    vertex = math.log(260.0)
    profile = 3.0 * (log_f - vertex) ** 2 + 10.0
    best, inside = _minimum(log_f, profile)
    assert inside and best == pytest.approx(vertex, abs=1e-9)
    assert _minimum(log_f, np.arange(5.0))[1] is False  # rising: the minimum is at the edge


def test_the_rise_is_the_parabolas_at_a_20_percent_step():
    log_f = np.log([200.0, 240.0, 288.0, 346.0, 415.0])
    vertex, depth, floor = math.log(260.0), 40.0, 500.0
    profile = depth * (log_f - vertex) ** 2 + floor
    assert _rise(log_f, profile) == pytest.approx(depth * RISE_STEP**2 / floor, rel=1e-9)
    assert _rise(log_f, np.arange(5.0) + 1.0) == 0.0  # minimum at the edge


def frames_with_profile(
    monkeypatch, depth: float, fovs, width: int, true_fov: float, frames: int = 24, unfitted: int = 0
):
    """estimate_focal with every frame's cost a parabola in log focal length around ``true_fov``
    (plus a little noise), ``depth`` its relative rise at a 20 % step: the decision rule alone.
    ``unfitted`` frames fail (NaN) at one focal length, as a fit that does not converge does."""
    log_true = math.log((width / 2) / math.tan(math.radians(true_fov) / 2))
    rng = np.random.default_rng(1)

    def profile(observations, picks, body, layout, w, h, grid, intrinsics_dist=None):
        log_f = np.log([(w / 2) / math.tan(math.radians(f) / 2) for f in grid])
        shape = 1.0 + depth * ((log_f - log_true) / RISE_STEP) ** 2
        costs = 10.0 * shape[None, :] * (1.0 + 1e-4 * rng.standard_normal((len(picks), len(grid))))
        costs[:unfitted, 0] = np.nan
        return costs

    monkeypatch.setattr(focal, "_profile", profile)
    no_stride = stride.StrideEstimate(math.nan, math.nan, math.nan, 0, 0.0, frames)  # a walk in place
    monkeypatch.setattr(focal, "stride_focal", lambda *a, **k: no_stride)
    kp = Keypoints("blazepose33", np.zeros((33, 2), np.float32), np.ones(33, np.float32), None)
    observations = [FocalObservation(i / 30.0, kp, 1.0) for i in range(frames)]
    return estimate_focal(observations, None, None, width, width, fovs=fovs, max_frames=frames)


def test_a_deep_profile_is_sure_at_its_vertex(monkeypatch):
    found = frames_with_profile(monkeypatch, 0.05, focal.GRID_FOV_DEG, 256, 50.0)
    assert found.sure, found.describe()
    assert found.fov_deg == pytest.approx(50.0, abs=1.0)
    assert found.rise == pytest.approx(0.05, rel=0.15)


def test_a_flat_profile_is_unsure_however_tight_its_bootstrap(monkeypatch):
    """A detector's systematic error is in every frame: the bootstrap is tight around whatever
    minimum it makes, so a profile that hardly rises must be called unsure."""
    found = frames_with_profile(monkeypatch, 0.005, focal.GRID_FOV_DEG, 256, 50.0)
    assert found.high_fov_deg - found.low_fov_deg < 2.0  # the bootstrap alone would say sure
    assert not found.sure and "changes by only" in found.reason, found.describe()


def test_a_deep_profile_from_too_few_fitted_frames_is_unsure(monkeypatch):
    """20 confident frames, 6 of them not fitted at one focal length: the 14 left make two
    bootstrap blocks, whose interval is tight around any minimum; the answer is given, never sure."""
    found = frames_with_profile(monkeypatch, 0.05, focal.GRID_FOV_DEG, 256, 50.0, frames=20, unfitted=6)
    assert found.frames == 14 and found.fov_deg == pytest.approx(50.0, abs=1.0)
    assert not found.sure and "frames fitted at every focal length" in found.reason, found.describe()
    assert frames_with_profile(monkeypatch, 0.05, focal.GRID_FOV_DEG, 256, 50.0, frames=20).sure


def test_too_few_frames_are_unsure(body):
    found = estimate_focal([], body, get_layout("blazepose33"), 256, 256)
    assert not found.sure and "confident frames" in found.reason


def test_a_person_standing_far_away_is_unsure(tmp_path_factory, body):
    truth = subject(
        tmp_path_factory, "still", num_frames=60, motion="still", fov_deg=40.0, camera_distance=6.0
    )
    found = estimate_focal(
        observations(body, truth), body, get_layout("blazepose33"), truth.size, truth.size,
        fovs=(30.0, 40.0, 52.0, 66.0, 84.0), max_frames=24,
    )  # fmt: skip
    assert not found.sure, found.describe()


@pytest.mark.slow
def test_a_walk_towards_the_camera_pins_the_focal_length(tmp_path_factory, body):
    truth = subject(tmp_path_factory, "approach", num_frames=240, motion="approach", fov_deg=75.0,
                    camera_distance=3.0)  # fmt: skip
    found = estimate_focal(observations(body, truth), body, get_layout("blazepose33"), truth.size, truth.size)
    error = truth.K[0, 0] / found.focal_px - 1.0
    assert abs(error) < 0.10, (found.describe(), true_fov(truth))


# ---- the planted feet (stg_node.tracking.stride) -------------------------------------------------


def walker(focal_error: float, speed: float = 1.2, fps: float = 30.0, seconds: float = 4.0, seed: int = 0):
    """Closed form: a pelvis walking straight at the camera at ``speed`` (m/s), the stance ankle
    planted (its depth offset from the pelvis grows as the pelvis comes closer), legs alternating
    every 0.5 s; the pelvis depth as a fit ``focal_error`` times the true focal length sees it."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 1.0 / fps)
    z = 6.0 - speed * t
    leg = (t // 0.5).astype(int) % 2
    start = np.floor(t / 0.5) * 0.5  # when the current stance began: the foot was put down under the pelvis
    offsets = np.full((len(t), 2), 0.1)
    offsets[np.arange(len(t)), leg] = speed * (t - start) - 0.3  # planted: z + d constant over a stance
    heights = np.full((len(t), 2), -0.8)
    heights[np.arange(len(t)), 1 - leg] = -0.7  # the swing foot lifted
    noisy_z = focal_error * z + rng.normal(0.0, 0.01, len(t))
    return t, noisy_z, offsets + rng.normal(0.0, 0.005, offsets.shape), heights


def test_stance_runs_follow_the_lower_ankle():
    t, _, _, heights = walker(1.0)
    runs = stride.stance_runs(t, heights, 0.05)
    assert len(runs) == 8  # 4 s at two steps a second
    assert [leg for _, leg in runs] == [0, 1] * 4
    assert all(len(frames) == 9 for frames, _ in runs)  # 15 a stance, the 3 at each end left out
    heights[:, 1] = heights[:, 0]  # both feet down (standing): no stance to read
    assert stride.stance_runs(t, heights, 0.05) == []


@pytest.mark.parametrize("focal_error", [0.6, 1.0, 1.5])
def test_the_planted_scale_recovers_the_focal_error(focal_error):
    t, z, offsets, heights = walker(focal_error)
    runs = stride.stance_runs(t, heights, 0.05)
    s, rates, draws = stride.planted_scale(t, z, offsets, runs, np.random.default_rng(0), 100)
    assert s * focal_error == pytest.approx(1.0, rel=0.03)  # the fit's focal length times s is the truth
    assert np.percentile(draws, 84) / np.percentile(draws, 16) < 1.05


def test_a_pivoting_foot_does_not_pull_the_planted_scale():
    """One run where the body turns on the spot (the pelvis hardly moves, the foot slides): the
    weighted median ignores it; a least-squares ratio would not."""
    t, z, offsets, heights = walker(1.0)
    runs = stride.stance_runs(t, heights, 0.05)
    frames, leg = runs[3]
    z[frames] = z[frames][0] - 0.3 * (t[frames] - t[frames][0])  # the body slows ...
    offsets[frames, leg] = 2.0 * (t[frames] - t[frames][0])  # ... and the foot slides
    assert stride.planted_scale(t, z, offsets, runs)[0] == pytest.approx(1.0, rel=0.03)


def test_a_person_standing_still_gives_no_stride():
    t, _, offsets, heights = walker(1.0, speed=0.0)
    heights[:] = -0.8  # both feet on the floor
    runs = stride.stance_runs(t, heights, 0.05)
    s, _, _ = stride.planted_scale(t, np.full(len(t), 4.0), offsets, runs)
    assert runs == [] and math.isnan(s)


UNSETTLED = pytest.mark.xfail(
    strict=True,
    reason="issue 26, not met: the fit's depth travel does not scale with the trial focal length, so "
    "the passes overshoot and do not settle (30 deg read 38.9, 75 deg 64.6 with a wide interval)",
)


@pytest.mark.slow
@pytest.mark.parametrize(
    "fov, distance",
    [(45.0, 5.0), pytest.param(30.0, 6.5, marks=UNSETTLED), pytest.param(75.0, 3.5, marks=UNSETTLED)],
)
def test_planted_feet_pin_the_focal_length_at_any_distance(tmp_path_factory, body, fov, distance):
    """True keypoints of a walk in depth (feet planted by the generator): the stride cue alone,
    from the default 65 degrees, within 10 % of the truth, even far away (30 degrees, 5-8 m)
    where the perspective within the body says almost nothing."""
    truth = subject(tmp_path_factory, f"stride_{fov:g}", num_frames=120, motion="approach", fov_deg=fov,
                    camera_distance=distance)  # fmt: skip
    default = (truth.size / 2) / math.tan(math.radians(65.0) / 2)
    found = stride.stride_focal(observations(body, truth), body, get_layout("blazepose33"), truth.size,
                                truth.size, default)  # fmt: skip
    assert abs(truth.K[0, 0] / found.focal_px - 1.0) < 0.10, (found, true_fov(truth))
    assert found.runs >= focal.MIN_STANCE_RUNS and found.relative < focal.SURE_RELATIVE


@pytest.mark.parametrize("speed, sure", [(1.2, True), (0.3, False)])
def test_the_stride_decides_only_for_a_plausible_walk(monkeypatch, speed, sure):
    """A tight stride estimate decides (cue "stride") when its legs walk at a walker's speed; legs
    that barely move in depth (a detector's flattened 3D points) leave it to the flat profile: unsure."""
    found_stride = stride.StrideEstimate(300.0, 290.0, 310.0, 6, 1.5, 120, speed, converged=True)
    frames_with_profile(monkeypatch, 0.005, focal.GRID_FOV_DEG, 256, 50.0)  # installs the flat profile
    monkeypatch.setattr(focal, "stride_focal", lambda *a, **k: found_stride)
    kp = Keypoints("blazepose33", np.zeros((33, 2), np.float32), np.ones(33, np.float32), None)
    found = estimate_focal([FocalObservation(i / 30.0, kp, 1.0) for i in range(24)], None, None, 256, 256)
    assert found.sure is sure, found.describe()
    assert (found.cue == "stride") is sure and found.stride["speed_mps"] == speed
    if sure:
        assert found.focal_px == 300.0 and found.low_fov_deg < found.fov_deg < found.high_fov_deg
