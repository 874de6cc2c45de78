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
from stg_node.tracking import focal
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


def frames_with_profile(monkeypatch, depth: float, fovs, width: int, true_fov: float, frames: int = 24):
    """estimate_focal with every frame's cost a parabola in log focal length around ``true_fov``
    (plus a little noise), ``depth`` its relative rise at a 20 % step: the decision rule alone."""
    log_true = math.log((width / 2) / math.tan(math.radians(true_fov) / 2))
    rng = np.random.default_rng(1)

    def profile(observations, picks, body, layout, w, h, grid, intrinsics_dist=None):
        log_f = np.log([(w / 2) / math.tan(math.radians(f) / 2) for f in grid])
        shape = 1.0 + depth * ((log_f - log_true) / RISE_STEP) ** 2
        return 10.0 * shape[None, :] * (1.0 + 1e-4 * rng.standard_normal((len(picks), len(grid))))

    monkeypatch.setattr(focal, "_profile", profile)
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
