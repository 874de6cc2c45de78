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
from stg_node.tracking.body_points import BodyKeypoints
from stg_node.tracking.focal import FocalObservation, _minimum, estimate_focal, fov_of
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
