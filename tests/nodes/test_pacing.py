"""The renderer's rate cap (stg_node/nodes/pacing.py) against arrival schedules worked out by hand."""

from __future__ import annotations

import numpy as np
import pytest

from stg_node.nodes.pacing import Pacer


def rendered(arrivals, rate_hz):
    """Serve each arrival as the renderer does: render when the cap allows, waiting for it at most
    until the next arrival replaces the pose (then the waiting pose is dropped)."""
    pacer = Pacer(rate_hz, now=arrivals[0])
    done = 0
    for i, t in enumerate(arrivals):
        go = t + pacer.wait_s(t)
        nxt = arrivals[i + 1] if i + 1 < len(arrivals) else np.inf
        if go < nxt:
            pacer.take(go)
            done += 1
    return done


def test_poses_at_the_cap_with_jitter_are_all_rendered():
    rng = np.random.default_rng(0)
    arrivals = np.arange(300) / 30.0 + rng.uniform(-0.006, 0.006, 300)  # a 30 fps camera, +-6 ms
    assert rendered(arrivals, 30.0) == 300
    # the old rule (at least 1/rate since the last render) dropped the early ones
    last, old = -np.inf, 0
    for t in arrivals:
        if t - last >= 1 / 30.0:
            last, old = t, old + 1
    assert old < 250


def test_the_average_rate_stays_at_the_cap():
    arrivals = np.arange(600) / 60.0  # poses at 60 Hz, a 30 Hz cap: 10 s, one pose in two
    assert rendered(arrivals, 30.0) == pytest.approx(300, abs=2)


def test_credit_is_capped_at_the_burst():
    pacer = Pacer(10.0, burst=2.0, now=0.0)
    assert pacer.ready(100.0)  # a long idle spell banks two renders, not a thousand
    pacer.take(100.0)
    pacer.take(100.0)
    assert not pacer.ready(100.0)
    assert pacer.wait_s(100.0) == pytest.approx(0.1)


@pytest.mark.parametrize("rate, burst", [(0.0, 2.0), (-1.0, 2.0), (30.0, 0.5)])
def test_a_bad_cap_is_refused(rate, burst):
    with pytest.raises(ValueError, match="Pacer"):
        Pacer(rate, burst)
