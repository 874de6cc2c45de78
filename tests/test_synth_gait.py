"""The synthetic walks plant their feet (stg_node.data.synth.gait): the stance ankle keeps its place
on the floor while the body passes over it, checked on the body model's own posed joints (an
independent forward pass of the generated SMPL parameters, not the generator's integration)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from stg_node.body import load_body_model
from stg_node.body.motion import drive_body
from stg_node.data.synth.gait import ANKLES, Feet, stance_legs
from stg_node.data.synth.generate import _body_joints
from stg_node.data.synth.motions import make_motion

FPS = 30.0


@pytest.fixture(scope="module")
def body():
    return load_body_model()


def skeleton_of(body, betas):
    return lambda poses, Rh: _body_joints(body, betas, poses, Rh)


def world_joints(body, motion) -> np.ndarray:
    with torch.no_grad():
        return drive_body(body, motion).joints.double().numpy()


def stance_slip_mm(joints: np.ndarray) -> np.ndarray:
    """(N - 1,) how far the stance ankle moves over the floor plane in each step, millimetres."""
    leg = np.asarray(ANKLES)[stance_legs(joints)]
    i = np.arange(len(joints) - 1)
    return 1000 * np.linalg.norm(joints[i, leg, :2] - joints[i + 1, leg, :2], axis=1)


@pytest.mark.parametrize("name", ["walk", "approach"])
def test_the_stance_foot_stays_planted_while_the_body_walks(body, name):
    betas = np.random.default_rng(2).normal(0, 1, 10).astype(np.float32)  # not the mean body
    planted = make_motion(
        name, 120, FPS, np.random.default_rng(5), betas=betas, skeleton=skeleton_of(body, betas)
    )
    sliding = make_motion(name, 120, FPS, np.random.default_rng(5), betas=betas)
    walking = np.ones(119, bool)
    if name == "approach":  # turning round at the ends steps on the spot: only the legs count
        speed = np.linalg.norm(np.diff(sliding.Th[:, :2], axis=0), axis=1) * FPS
        walking = speed > 0.99 * speed.max()
    slip = stance_slip_mm(world_joints(body, planted))[walking]
    assert walking.sum() > 30 and slip.max() < 1.0, slip.max()  # float32 parameters: sub-millimetre
    assert np.median(stance_slip_mm(world_joints(body, sliding))[walking]) > 10.0  # the old gait slid
    # The body travels: a real walking speed, no jumps.
    speed = np.linalg.norm(np.diff(planted.Th[:, :2], axis=0), axis=1)[walking] * FPS
    assert 0.5 < speed.mean() < 2.0 and speed.max() < 3.0


def test_motions_that_do_not_walk_are_unchanged_by_the_skeleton(body):
    betas = np.zeros(10, np.float32)
    for name, kw in (("turn", {}), ("dance", {}), ("walk", {"train_yaw_deg": 90.0})):
        plain = make_motion(name, 60, FPS, np.random.default_rng(1), 45, **kw)
        with_feet = make_motion(
            name, 60, FPS, np.random.default_rng(1), 45, skeleton=skeleton_of(body, betas), **kw
        )
        for field in ("poses", "Rh", "Th"):
            np.testing.assert_array_equal(
                getattr(plain, field), getattr(with_feet, field), err_msg=f"{name} {field}"
            )


def test_a_planted_step_keeps_a_turning_ankle_in_place():
    """Closed form: an ankle at a fixed body offset, the body turning by 90 degrees in a step."""
    joints = np.zeros((2, 24, 3))
    joints[:, ANKLES[0]] = [0.1, -0.2, 0.05]  # left ankle lower: the stance leg
    joints[:, ANKLES[1]] = [-0.1, 0.3, 0.2]
    step = Feet(joints).planted_step(0, 0.0, np.pi / 2)
    turned = np.array([0.2, 0.1])  # (0.1, -0.2) turned by +90 degrees about z
    np.testing.assert_allclose(step, np.array([0.1, -0.2]) - turned, atol=1e-12)
