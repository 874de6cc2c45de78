"""The C++ densification statistics (stg_node.splat.densify_ops) against the density strategy's
torch code (DensifyStrategy._accumulate_torch and _accumulate_help_torch, run in float64 as the
oracle): every per-Gaussian statistic after several steps of random sightings, with and without
a table index, the depth test, the flow and the rendered motion, the error weight, a second
camera, and pixel centres on rounding ties."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from stg_node.avatar.config import DensifyConfig
from stg_node.avatar.densify import DensifyInputs, DensifyStrategy
from stg_node.avatar.motion_basis import MotionBases
from stg_node.splat import densify_ops

pytestmark = pytest.mark.usefixtures("cpu_kernels")  # skips where the kernels cannot build

ROWS = 400  # table rows
STATS = ("grad_sum", "vis_count", "front_count", "m_per_px", "flow_w", "resid_w")


def fresh_state(dtype, cameras: int, gen) -> dict:
    """Statistics part way through an interval: some rows with running means, some at zero."""
    state = {}
    for name in STATS:
        v = torch.rand(ROWS, generator=gen, dtype=torch.float64) * 3
        state[name] = torch.where(torch.rand(ROWS, generator=gen, dtype=torch.float64) < 0.3, 0.0, v).to(
            dtype
        )
    state["resid_cam"] = torch.rand(ROWS, cameras, generator=gen, dtype=torch.float64).to(dtype)
    return state


def sightings(gen, *, indexed: bool, depth: bool, flow: bool, rendered_flow: bool, radii_2d: bool, slot: int):
    """One step's rendered Gaussians of a 37x23 crop at (5, 7) of a 60x50 frame."""
    w, h, x0, y0 = 37, 23, 5, 7
    n = 300 if indexed else ROWS
    xy = torch.rand(n, 2, generator=gen, dtype=torch.float64) * torch.tensor([w + 8.0, h + 8.0]) - 4.0
    xy[::7] = torch.floor(xy[::7]) + 0.5  # ties: torch rounds half to even
    means2d = xy.float()
    means2d.absgrad = torch.randn(n, 2, generator=gen).abs() * 1e-3
    radii = torch.randint(0, 3, (n, 2) if radii_2d else (n,), generator=gen, dtype=torch.int32)
    index = torch.randperm(ROWS, generator=gen)[:n] if indexed else None
    info = {"radii": radii, "means2d": means2d}
    if depth:
        info["depths"] = (1.0 + 2.0 * torch.rand(n, generator=gen)).float()
    frame = SimpleNamespace(
        forward=(
            4
            * np.random.default_rng(int(torch.randint(1 << 30, (1,), generator=gen))).standard_normal(
                (50, 60, 2)
            )
        ).astype(np.float32),
        valid_forward=np.random.default_rng(3).random((50, 60)) > 0.3,
    )
    return DensifyInputs(
        iteration=1,
        info=info,
        index=index,
        camera=SimpleNamespace(K=torch.tensor([[300.0, 0, 20], [0, 300.0, 12], [0, 0, 1]])),
        crop=(x0, y0, w, h),
        render=torch.rand(h, w, 3, generator=gen),
        target=torch.rand(h, w, 3, generator=gen),
        mask=None,
        flow=frame if flow else None,
        u=0.0,
        bones=None,
        generator=gen,
        motion_threshold_px=1.0,
        time_range=(0.0, 1.0),
        surface=None,
        rendered_flow=torch.randn(h, w, 2, generator=gen) if rendered_flow else None,
        rendered_depth=(1.0 + 2.0 * torch.rand(h, w, generator=gen)) if depth else None,
        camera_slot=slot,
    )


def as_double(inputs: DensifyInputs) -> DensifyInputs:
    info = dict(inputs.info)
    means2d = info["means2d"].double()
    means2d.absgrad = inputs.info["means2d"].absgrad.double()
    info["means2d"] = means2d
    if "depths" in info:
        info["depths"] = info["depths"].double()
    out = SimpleNamespace(**vars(inputs))
    out.info = info
    for name in ("render", "target", "rendered_flow", "rendered_depth"):
        t = getattr(inputs, name)
        setattr(out, name, None if t is None else t.double())
    out.camera = SimpleNamespace(K=inputs.camera.K.double())
    return out


CASES = [
    dict(
        indexed=False,
        depth=False,
        flow=False,
        rendered_flow=False,
        radii_2d=False,
        slot=0,
        clone_on_error=False,
    ),
    dict(
        indexed=True, depth=True, flow=True, rendered_flow=True, radii_2d=True, slot=0, clone_on_error=False
    ),
    dict(
        indexed=True, depth=True, flow=True, rendered_flow=False, radii_2d=True, slot=0, clone_on_error=True
    ),
    dict(
        indexed=False, depth=False, flow=True, rendered_flow=True, radii_2d=False, slot=1, clone_on_error=True
    ),
    dict(
        indexed=True, depth=True, flow=True, rendered_flow=True, radii_2d=True, slot=2, clone_on_error=False
    ),
]


@pytest.mark.parametrize(
    "case", CASES, ids=lambda c: "-".join(k for k, v in c.items() if v is True) or "plain"
)
def test_sightings_kernel_matches_torch(case):
    case = dict(case)
    clone_on_error = case.pop("clone_on_error")
    config = DensifyConfig(clone_on_error=clone_on_error, occlusion_m=0.3)
    strategy = DensifyStrategy(config, total_iterations=100)
    gen = torch.Generator().manual_seed(7)
    state = fresh_state(torch.float32, cameras=2, gen=gen)
    oracle = {k: v.double() for k, v in state.items()}
    for _ in range(4):
        inputs = sightings(gen, **case)
        grad = inputs.info["means2d"].absgrad
        assert strategy._accumulate_kernel(state, inputs, grad)
        d = as_double(inputs)
        strategy._accumulate_torch(oracle, d, d.info["means2d"].absgrad)
    if case["slot"] == 2:  # a third camera: its column added by both
        assert state["resid_cam"].shape == oracle["resid_cam"].shape == (ROWS, 3)
    for name in (*STATS, "resid_cam"):
        torch.testing.assert_close(state[name].double(), oracle[name], rtol=2e-6, atol=1e-6, msg=name)
    moved = sum(
        int(
            (
                state[n].double()
                != fresh_state(torch.float32, 2, torch.Generator().manual_seed(7))[n].double()[
                    : state[n].shape[0]
                ]
            ).any()
        )
        for n in ("grad_sum", "vis_count")
    )
    assert moved == 2  # the sightings changed the statistics


def test_sightings_kernel_declines_what_it_cannot_take():
    """Float64 statistics go the torch way (the kernel reports it did nothing)."""
    strategy = DensifyStrategy(DensifyConfig(), total_iterations=100)
    gen = torch.Generator().manual_seed(1)
    state = {k: v.double() for k, v in fresh_state(torch.float32, 1, gen).items()}
    before = {k: v.clone() for k, v in state.items()}
    inputs = sightings(gen, indexed=False, depth=True, flow=True, rendered_flow=True, radii_2d=False, slot=0)
    assert not strategy._accumulate_kernel(state, inputs, inputs.info["means2d"].absgrad)
    for k in before:
        assert torch.equal(state[k], before[k])
    # a strided statistic (written in place: no contiguous copy may stand in for it)
    state = fresh_state(torch.float32, 1, gen)
    state["flow_w"] = torch.zeros(ROWS, 2)[:, 0]
    assert not strategy._accumulate_kernel(state, inputs, inputs.info["means2d"].absgrad)


class Table(dict):
    @property
    def num(self) -> int:
        return self["means"].shape[0]


@pytest.mark.parametrize("count", [24, 6, 30])
@pytest.mark.parametrize("moving_share", [0.2, 0.8])
@pytest.mark.parametrize("with_delta", [True, False])
def test_motion_help_kernel_matches_torch(count, moving_share, with_delta):
    gen = torch.Generator().manual_seed(count)
    n = 500
    weights = torch.softmax(3 * torch.randn(n, 24, generator=gen), dim=1)
    delta = 0.5 * torch.randn(n, 24, generator=gen) if with_delta else None
    bases = MotionBases(count, 1.0, knots=3, values=0.1 * torch.randn(count, 3, 3, 4, generator=gen))
    means = torch.randn(n, 3, generator=gen)
    grad = torch.randn(n, 3, generator=gen)
    grad[::5] = 0.0  # rows the image did not reach
    gate = torch.rand(n, generator=gen) < moving_share
    u = 1.3
    dot, norm = torch.rand(n, generator=gen), torch.rand(n, generator=gen)
    expect = {"help_dot": dot.double(), "help_norm": norm.double()}
    table = Table(skin_weights=weights.double(), means=means.double())
    if with_delta:
        table["skin_delta"] = delta.double()
    motions64 = bases.at(u).detach().double()
    bases64 = SimpleNamespace(count=count, at=lambda _u: motions64)
    DensifyStrategy._accumulate_help_torch(table, bases64, gate, grad.double(), expect, SimpleNamespace(u=u))
    got = {"help_dot": dot.clone(), "help_norm": norm.clone()}
    densify_ops.motion_help(
        weights, delta, 1e-4, bases.at(u).detach(), means, grad, gate, got["help_dot"], got["help_norm"]
    )
    for name in got:
        torch.testing.assert_close(got[name].double(), expect[name], rtol=1e-5, atol=1e-6, msg=name)
    assert torch.equal(got["help_dot"][gate], dot[gate])  # moving rows untouched
    assert not torch.equal(got["help_dot"], dot)
