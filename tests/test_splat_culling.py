"""splat.culling.may_be_visible: the C++ test against its torch reference, and against the
rasterizer itself: it never drops a Gaussian the rasterizer keeps, and drops most of those far
out of view."""

from __future__ import annotations

import pytest
import torch

from stg_node.splat import culling, rasterize
from stg_node.splat.scenes import front_camera, person_sized_scene

pytestmark = pytest.mark.usefixtures("cpu_kernels")  # skips where the kernels cannot build


def cameras(size=128):
    """The framing camera, a four-times zoom on the chest, one looking away, one off-centre."""
    viewmat, K = front_camera(size, size)
    zoom = K.clone()
    zoom[0, 0] *= 4
    zoom[1, 1] *= 4
    centre = -viewmat[:3, :3].T @ viewmat[:3, 3]
    away = viewmat.clone()
    away[:3, :3] = torch.diag(torch.tensor([-1.0, 1.0, -1.0])) @ viewmat[:3, :3]  # turned round: all behind
    away[:3, 3] = -away[:3, :3] @ centre
    shifted = K.clone()
    shifted[0, 2] += 0.45 * size
    return {"front": (viewmat, K), "zoom": (viewmat, zoom), "away": (away, K), "shifted": (viewmat, shifted)}


@pytest.mark.parametrize("max_scale", [0.03, 0.2])
@pytest.mark.parametrize("name", ["front", "zoom", "away", "shifted"])
def test_never_drops_what_the_rasterizer_draws(name, max_scale):
    scene = person_sized_scene(4000, seed=1, max_scale=max_scale)
    viewmat, K = cameras()[name]
    means, quats, scales, opacities, colors = scene.params()
    _, _, info = rasterize(means, quats, scales, opacities, colors, viewmat, K, 128, 128, backend="cpu")
    kept = culling.may_be_visible(means, scales, viewmat, K, 128, 128)
    reference = culling.may_be_visible_torch(means, scales, viewmat, K, 128, 128)
    assert kept.dtype == torch.bool and kept.shape == (4000,)
    assert bool((kept | ~info["visible"]).all())  # every visible Gaussian is kept
    # float32 (torch) and float64 (C++) may disagree only within the margin: on no row here
    assert torch.equal(kept, reference)
    if name == "away":
        assert not bool(kept.any())
    if name == "zoom" and max_scale == 0.03:
        assert int(kept.sum()) < 0.6 * 4000  # the legs and head are out of view


def test_depth_planes_and_non_finite_rows():
    viewmat, K = cameras()["front"]
    means = torch.tensor([[0.0, 0.9, 2.995], [0.0, 0.9, -1e12], [float("nan"), 0.0, 0.0], [0.0, 0.9, 0.0]])
    scales = torch.full((4, 3), 0.01)
    kept = culling.may_be_visible(means, scales, viewmat, K, 128, 128, near_plane=0.01)
    # camera z of the first is 0.005 (< near), the second beyond the far plane; the NaN is kept so
    # that the rasterizer's input checks report it
    assert kept.tolist() == [False, False, True, True]
    assert culling.may_be_visible_torch(means, scales, viewmat, K, 128, 128).tolist() == kept.tolist()
