"""Non-rigid part: polynomial motion, rotation and temporal opacity in closed form; bounded time."""

from __future__ import annotations

import math

import torch

from stg_node.avatar import spacetime
from stg_node.avatar.config import ModelConfig
from stg_node.avatar.gaussians import GaussianTable, new_columns


def _table(n=5, seed=0, **model):
    model.setdefault("motion_basis", 0)  # per-Gaussian polynomials (the shared bases: motion_priors tests)
    cfg = ModelConfig(num_gaussians=n, max_gaussians=max(n, 10), **model)
    gen = torch.Generator().manual_seed(seed)
    cols = new_columns(
        cfg,
        torch.randn(n, 3, generator=gen),
        torch.softmax(torch.randn(n, 24, generator=gen), 1),
        0.01,
        t_center=0.0,
        t_scale=0.3,
        generator=gen,
    )
    cols["motion"] = torch.randn(cols["motion"].shape, generator=gen) * 0.01
    cols["rot_motion"] = torch.randn(cols["rot_motion"].shape, generator=gen) * 0.1
    cols["t_center"] = torch.rand(n, generator=gen)
    return cfg, GaussianTable(cols)


def test_polynomial_terms_match_the_closed_form_near_the_temporal_centre():
    cfg, table = _table()
    u = 0.42
    st = spacetime.evaluate(table, u, cfg.time_horizon, temporal_opacity=True)
    dt = u - table["t_center"]
    w = table["t_log_scale"].exp().clamp_max(cfg.time_horizon)  # the window, at most the horizon
    tau = torch.tanh(dt / w)
    b = table["motion"]
    expected = b[:, 0] * tau[:, None] + b[:, 1] * tau[:, None] ** 2
    assert torch.allclose(st.offsets, expected, atol=1e-7)
    assert torch.allclose(st.quats, table["quats"] + table["rot_motion"][:, 0] * tau[:, None], atol=1e-7)
    s = table["t_log_scale"].exp()
    assert torch.allclose(st.temporal, torch.exp(-((dt / s) ** 2)))
    # tanh is the identity to first order: for |dt| << h the bounded time is the raw time.
    small = spacetime.local_time(0.001, torch.zeros(1), 0.5)[1]
    assert math.isclose(float(small), 0.002, rel_tol=1e-5)


def test_ten_thousand_frames_stay_bounded_and_finite():
    cfg, table = _table(n=50)
    with torch.no_grad():
        table["motion"].mul_(100.0)  # large coefficients on purpose
    bound = float(table["motion"].detach().abs().sum(1).max())  # |tau| < 1
    for frame in (0, 1, 9_999, 10_000, 1_000_000):
        u = frame / 30.0
        st = spacetime.evaluate(table, u, cfg.time_horizon, temporal_opacity=True)
        assert (
            torch.isfinite(st.offsets).all()
            and torch.isfinite(st.quats).all()
            and torch.isfinite(st.temporal).all()
        )
        assert float(st.offsets.detach().abs().max()) <= bound + 1e-6
    # Before the first frame too (negative local time).
    st = spacetime.evaluate(table, -1e4, cfg.time_horizon, temporal_opacity=True)
    assert torch.isfinite(st.offsets).all()


def test_velocity_is_the_time_derivative_of_the_offset():
    cfg, table = _table()
    u, eps = 0.3, 1e-3
    ahead = spacetime.evaluate(table, u + eps, cfg.time_horizon, temporal_opacity=False).offsets
    behind = spacetime.evaluate(table, u - eps, cfg.time_horizon, temporal_opacity=False).offsets
    numeric = (ahead - behind) / (2 * eps)
    assert torch.allclose(spacetime.velocity(table, u, cfg.time_horizon), numeric, atol=1e-5)


def test_skipping_inactive_rows_changes_nothing_but_the_work():
    cfg, table = _table(n=20)
    with torch.no_grad():
        table["motion"][::2] = 0
        table["rot_motion"][::2] = 0
    full = spacetime.evaluate(table, 0.7, cfg.time_horizon, temporal_opacity=True)
    skipped = spacetime.evaluate(table, 0.7, cfg.time_horizon, temporal_opacity=True, skip_inactive=True)
    assert torch.equal(full.offsets, skipped.offsets)
    assert torch.equal(full.quats, skipped.quats)
    assert torch.equal(full.temporal, skipped.temporal)
    assert int(table.motion_active().sum()) == 10
    # Nothing moving and every window persistent: the rigid part alone, nothing evaluated.
    with torch.no_grad():
        table["motion"].zero_()
        table["rot_motion"].zero_()
        table["t_log_scale"].fill_(math.log(2 * spacetime.PERSISTENT_SCALE))
    still = spacetime.evaluate(table, 0.7, cfg.time_horizon, temporal_opacity=True, skip_inactive=True)
    assert still.offsets is None and still.temporal is None and still.quats is table["quats"]
    every = spacetime.evaluate(table, 0.7, cfg.time_horizon, temporal_opacity=True)
    assert torch.equal(every.offsets, torch.zeros(20, 3)) and torch.equal(every.temporal, torch.ones(20))


def test_spacetime_off_gives_no_terms():
    cfg = ModelConfig(num_gaussians=3, spacetime=False)
    cols = new_columns(cfg, torch.zeros(3, 3), torch.full((3, 24), 1 / 24), 0.01)
    assert "motion" not in cols and "t_center" not in cols
    st = spacetime.evaluate(GaussianTable(cols), 1.0, 1.0, temporal_opacity=False)
    assert st.offsets is None and st.temporal is None
