"""tools/model_census.py --weights against closed forms: a Gaussian's blend weight summed over a
view is the sum of its analytic alpha (times the transmittance left by those in front of it), a
Gaussian behind the camera or outside the view gets 0, and views add up per model row."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))

import model_census  # noqa: E402

from stg_node.splat import constants  # noqa: E402
from stg_node.splat.api import available_backends  # noqa: E402

BACKENDS = [b for b in available_backends() if b != "cuda"]
WIDTH, HEIGHT, F, CX, CY = 40, 30, 120.0, 17.3, 14.6


def _analytic_alpha(scale: float, depth: float, opacity: float) -> np.ndarray:
    """alpha(u, v) of an isotropic Gaussian on the optical axis (EWA with the 0.3 px^2 low-pass)."""
    var = (F * scale / depth) ** 2 + constants.LOW_PASS_EPS2D
    v, u = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float64)
    d2 = (u + 0.5 - CX) ** 2 + (v + 0.5 - CY) ** 2
    alpha = np.minimum(opacity * np.exp(-0.5 * d2 / var), constants.ALPHA_MAX)
    return np.where(alpha >= constants.ALPHA_MIN, alpha, 0.0)


def _weights(backend: str, means, scales, opacities) -> np.ndarray:
    dtype = torch.float64 if backend == "torch" else torch.float32
    n = len(means)
    K = torch.tensor([[F, 0.0, CX], [0.0, F, CY], [0.0, 0.0, 1.0]], dtype=dtype)
    return model_census.view_blend_weights(
        torch.tensor(means, dtype=dtype),
        torch.tensor([[1.0, 0.0, 0.0, 0.0]] * n, dtype=dtype),
        torch.tensor([[s] * 3 for s in scales], dtype=dtype),
        torch.tensor(opacities, dtype=dtype),
        torch.eye(4, dtype=dtype), K, WIDTH, HEIGHT, backend,
    )  # fmt: skip


@pytest.mark.parametrize("backend", BACKENDS)
def test_blend_weights_are_alpha_times_transmittance_summed_over_the_pixels(backend):
    """On the axis: a front Gaussian at 2 m, one behind it at 3 m, one behind the camera, one whose
    centre projects far outside the image. Only the first two cover pixels; the back one's weight is
    what the front one lets through."""
    means = [[0.0, 0.0, 2.0], [0.0, 0.0, 3.0], [0.0, 0.0, -2.0], [5.0, 0.0, 2.0]]
    scales, opacities = [0.05, 0.08, 0.05, 0.05], [0.6, 0.5, 0.9, 0.9]
    weights = _weights(backend, means, scales, opacities)
    front = _analytic_alpha(scales[0], 2.0, opacities[0])
    back = _analytic_alpha(scales[1], 3.0, opacities[1])
    expected = [front.sum(), (back * (1.0 - front)).sum(), 0.0, 0.0]
    assert expected[0] > 20 and expected[1] > 5  # both cover many pixels: the sums are not trivial
    np.testing.assert_allclose(weights, expected, rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_lone_gaussian_alone_in_the_view_sums_its_alpha(backend):
    """Without the one in front, the same back Gaussian gets its whole alpha: occlusion, not the
    renderer's bookkeeping, made the difference above."""
    weights = _weights(backend, [[0.0, 0.0, 3.0]], [0.08], [0.5])
    np.testing.assert_allclose(weights, [_analytic_alpha(0.08, 3.0, 0.5).sum()], rtol=1e-4)


def test_views_add_up_per_model_row_and_keep_each_rows_largest():
    """A view that posed every row, then one that posed rows 2 and 0 only (culled rows keep 0)."""
    views = [(None, np.array([1.0, 4.0, 0.5])), (np.array([2, 0]), np.array([3.0, 0.25]))]
    total, peak = model_census.sum_over_views(3, views)
    np.testing.assert_allclose(total, [1.25, 4.0, 3.5])
    np.testing.assert_allclose(peak, [1.0, 4.0, 3.0])


def test_a_trained_runs_weights_add_up_to_its_rendered_alpha(tmp_path):
    """End to end on a tiny run: the blend weights of all Gaussians in a view sum to the view's
    alpha (compositing), so over the training views they sum to the renderer's alpha images, read
    back as uint8 (half a level a pixel of rounding)."""
    from stg_node.avatar.data_spec import DataSpec
    from stg_node.avatar.loading import corrected, load_run_renderer
    from stg_node.cli import train as train_cli
    from stg_node.data.synth.generate import SynthConfig, generate

    data, run, size = tmp_path / "synth", tmp_path / "run", 64
    generate(
        SynthConfig(out=data, num_frames=4, size=size, num_novel_views=1, view_every=2, supersample=1),
        progress=False,
    )
    args = ["--data", str(data), "--out", str(run), "--iters", "2", "--format", "synthetic"]
    assert train_cli.main([*args, "--preset", "fast", "--size", str(size), "--no-progress"]) == 0
    total, peak = model_census.blend_weights(run)
    _, renderer, corrections, _ = load_run_renderer(run)
    assert total.shape == peak.shape == (renderer.model.table.num,)
    assert (peak >= 0).all() and (peak <= total + 1e-9).all()
    views = DataSpec(str(data), "synthetic", size=size).open("train")
    alpha = 0.0
    for sample in views:
        smpl = corrected(sample.smpl, corrections.get(sample.index))
        alpha += renderer.render(sample.camera, smpl, sample.time).alpha.astype(np.float64).sum() / 255
    assert alpha > 50  # the body covers many pixels
    assert abs(total.sum() - alpha) <= 0.5 / 255 * size * size * len(views) + 1e-3 * alpha
