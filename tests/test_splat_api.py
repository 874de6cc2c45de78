"""The public rasterize() contract: argument checking, backend choice, the info dict,
background and depth handling, and the torch reference's memory chunking."""

from __future__ import annotations

import logging

import pytest
import torch

from stg_node.splat import api, rasterize, torch_reference
from stg_node.splat.scenes import random_scene


def _args(n=4, channels=3):
    scene, viewmat, K = random_scene(n, 24, 16, seed=1, channels=channels)
    return list(scene.params()) + [viewmat, K, 24, 16]


def _call(args, **kw):
    return rasterize(*args, backend="torch", **kw)


@pytest.mark.parametrize(
    "index,value,message",
    [
        (0, torch.zeros(4, 2), r"means must be \[N, 3\], got \[4, 2\]"),
        (1, torch.zeros(4, 3), r"quats must be \[4, 4\] for N=4 Gaussians, got \[4, 3\]"),
        (2, torch.zeros(3, 3), r"scales must be \[4, 3\] for N=4 Gaussians, got \[3, 3\]"),
        (3, torch.zeros(4, 1), r"opacities must be \[4\] for N=4 Gaussians, got \[4, 1\]"),
        (4, torch.zeros(4), r"colors must be \[N, C\] with N=4 and C >= 1, got \[4\]"),
        (4, torch.zeros(4, 0), r"colors must be \[N, C\]"),
        (5, torch.eye(3), r"viewmat must be a \[4, 4\] world-to-camera matrix, got \[3, 3\]"),
        (6, torch.eye(4), r"K must be a \[3, 3\] intrinsics matrix, got \[4, 4\]"),
    ],
)
def test_wrong_shapes_are_named(index, value, message):
    args = _args()
    args[index] = value
    with pytest.raises(ValueError, match=message):
        _call(args)


def test_wrong_types_sizes_and_camera_are_clear_errors():
    args = _args()
    bad = list(args)
    bad[2] = bad[2].double()
    with pytest.raises(TypeError, match="scales is torch.float64 but means is torch.float32"):
        _call(bad)
    bad = list(args)
    bad[0] = bad[0].long()
    with pytest.raises(TypeError, match="means must be a floating-point tensor"):
        _call(bad)
    bad = list(args)
    bad[0] = bad[0].numpy()
    with pytest.raises(TypeError, match="means must be a torch.Tensor"):
        _call(bad)
    for w, h, msg in [
        (-1, 16, "width must be >= 0"),
        (24, -1, "height must be >= 0"),
        (24.0, 16, "width must be an int"),
    ]:
        bad = list(args)
        bad[7], bad[8] = w, h
        with pytest.raises((ValueError, TypeError), match=msg):
            _call(bad)
    bad = list(args)
    bad[5] = bad[5].clone()
    bad[5][3, 0] = 1.0
    with pytest.raises(ValueError, match="viewmat's last row must be"):
        _call(bad)
    bad = list(args)
    bad[6] = bad[6].clone()
    bad[6][0, 1] = 3.0
    with pytest.raises(ValueError, match="no skew"):
        _call(bad)
    bad = list(args)
    bad[6] = bad[6].clone()
    bad[6][1, 1] = -1.0
    with pytest.raises(ValueError, match="positive focal lengths"):
        _call(bad)
    bad = list(args)
    bad[2] = -bad[2]
    with pytest.raises(ValueError, match="scales must be activated"):
        _call(bad)
    with pytest.raises(ValueError, match=r"background must be \[C\] = \[3\]"):
        _call(args, background=torch.zeros(4))
    with pytest.raises(ValueError, match="unknown backend 'gpu'"):
        rasterize(*args, backend="gpu")
    with pytest.raises(ValueError, match="backend='cuda' needs CUDA tensors"):
        rasterize(*args, backend="cuda")
    with pytest.raises(ValueError, match="depth_mode must be one of"):
        _call(args, depth_mode="median")
    with pytest.raises(ValueError, match="need 0 < near_plane < far_plane"):
        _call(args, near_plane=0.0)
    with pytest.raises(ValueError, match="need 0 < near_plane < far_plane"):
        _call(args, near_plane=2.0, far_plane=1.0)
    with pytest.raises(ValueError, match="eps2d and radius_clip must be >= 0"):
        _call(args, eps2d=-0.1)
    with pytest.raises(ValueError, match="max_intersections must be >= 1"):
        _call(args, max_intersections=0)


def test_info_carries_what_densification_needs():
    args = [
        t.requires_grad_(True) if isinstance(t, torch.Tensor) and i < 5 else t
        for i, t in enumerate(_args(30))
    ]
    image, alpha, info = _call(args, render_depth=True)
    n = 30
    assert info["backend"] == "torch"
    assert info["means2d"].shape == (n, 2) and info["means2d"].requires_grad
    assert info["radii"].shape == (n, 2) and info["radii"].dtype == torch.int32
    assert info["visible"].shape == (n,) and info["visible"].dtype == torch.bool
    assert torch.equal(info["visible"], (info["radii"] > 0).all(dim=1))
    assert info["depths"].shape == (n,) and info["conics"].shape == (n, 3) and info["opacities"].shape == (n,)
    assert info["depth"].shape == (16, 24, 1)
    assert (info["width"], info["height"], info["tile_size"]) == (24, 16, 16)
    assert info["n_intersections"] >= int(info["visible"].sum())
    image.sum().backward()
    assert info["means2d"].grad.shape == (n, 2)
    assert info["means2d"].absgrad.shape == (n, 2)
    assert (info["means2d"].absgrad >= info["means2d"].grad.abs() - 1e-6).all()
    # Invisible Gaussians get no screen-space gradient.
    assert (info["means2d"].grad[~info["visible"]] == 0).all()


def test_background_is_blended_by_transmittance():
    args = _args(20)
    image0, alpha, _ = _call(args)
    bg = torch.tensor([0.3, 0.6, 0.9])
    image1, _, _ = _call(args, background=bg)
    assert torch.allclose(image1, image0 + (1 - alpha) * bg, atol=1e-6)
    image2, _, _ = _call(args, background=0.5)
    assert torch.allclose(image2, image0 + (1 - alpha) * 0.5, atol=1e-6)
    image3, _, _ = _call(args, background=[0.3, 0.6, 0.9])
    assert torch.allclose(image3, image1)


def test_any_number_of_channels():
    for channels in (1, 2, 7, 40):
        args = _args(10, channels)
        image, _, _ = _call(args)
        assert image.shape == (16, 24, channels)


def test_auto_picks_cpu_for_cpu_tensors_and_logs_once(monkeypatch, caplog):
    if api.cpu_backend_status() is not None:
        pytest.skip("C++ kernels unavailable")
    monkeypatch.setattr(api, "_logged_choices", set())
    args = _args()
    with caplog.at_level(logging.INFO, logger="stg_node.splat.api"):
        _, _, info = rasterize(*args)
        rasterize(*args)
    assert info["backend"] == "cpu"
    messages = [r.getMessage() for r in caplog.records if "splat backend" in r.getMessage()]
    assert messages == ["splat backend for cpu tensors: cpu (C++/OpenMP kernels)"]
    assert "torch" in api.available_backends() and "cpu" in api.available_backends()


def test_float64_inputs_keep_their_dtype_on_every_cpu_backend():
    args = [t.double() if isinstance(t, torch.Tensor) else t for t in _args(10)]
    for backend in [b for b in api.available_backends() if b != "cuda"]:
        image, alpha, info = rasterize(*args, backend=backend)
        assert image.dtype == alpha.dtype == torch.float64, backend


def test_torch_reference_memory_chunking_does_not_change_the_result():
    """Tiny pair budgets split blocks into many depth chunks; transmittance carries across."""
    scene, viewmat, K = random_scene(2000, 40, 30, seed=9, max_opacity=1.0)
    proj = torch_reference.project(*scene.params()[:4], viewmat, K, 40, 30)
    full, alpha_full = torch_reference.rasterize(proj, scene.colors, 40, 30)
    for block, pairs in [(8, 640), (40, 60_000)]:
        image, alpha = torch_reference.rasterize(
            proj, scene.colors, 40, 30, block_size=block, max_pairs=pairs
        )
        assert torch.allclose(image, full, atol=1e-6), (block, pairs)
        assert torch.allclose(alpha, alpha_full, atol=1e-6), (block, pairs)
    assert (alpha_full > 0.999).float().mean() > 0.05  # early termination exercised


def test_finite_check_is_exact_when_the_fast_sum_overflows():
    from stg_node.splat.validation import check_finite

    huge = torch.tensor([3e38, 3e38, 1.0])  # finite, but the float32 sum overflows to inf
    check_finite("means", huge)
    for bad in (float("nan"), float("inf"), -float("inf")):
        poisoned = huge.clone()
        poisoned[2] = bad
        with pytest.raises(ValueError, match=r"means contains non-finite values \(first at index \(2,\)"):
            check_finite("means", poisoned)
