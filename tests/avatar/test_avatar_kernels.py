"""The avatar's fast paths against today's torch path: the fused kernels inside AvatarModel.pose
(values and gradients), culling before colour, the per-stream colour cache, and a training run
with the kernels scoring like one with the torch reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from avatar_helpers import small_config

from stg_node.avatar import kernels
from stg_node.avatar.color_cache import ColorCache
from stg_node.avatar.model import Camera3, render
from stg_node.avatar.renderer import AvatarRenderer
from stg_node.avatar.trainer import Trainer
from stg_node.splat import build


@pytest.fixture(autouse=True)
def _kernels():
    try:
        build.load_kernels()
    except build.ExtensionUnavailable as exc:  # pragma: no cover - machines without a compiler
        pytest.skip(f"CPU kernels unavailable: {exc}")


@pytest.fixture(scope="module")
def trained(tiny_frames):
    """A model after 40 steps, then roughened so every path is exercised: learned weight
    corrections, moving Gaussians with rotations, a few transparent ones (culled rows). Per-Gaussian
    polynomials: the kernels skin whatever offsets the spacetime terms give, polynomial or bases."""
    trainer = Trainer(small_config(**{"model.motion_basis": 0}), seed=0)
    trainer.add_frames(tiny_frames)
    for _ in range(40):
        trainer.step()
    table = trainer.model.table
    gen = torch.Generator().manual_seed(3)
    with torch.no_grad():
        table["skin_delta"].copy_(0.3 * torch.randn(table["skin_delta"].shape, generator=gen))
        moving = torch.rand(table.num, generator=gen) < 0.3
        table["motion"][moving] = 0.01 * torch.randn(table["motion"][moving].shape, generator=gen)
        table["rot_motion"][moving] = 0.05 * torch.randn(table["rot_motion"][moving].shape, generator=gen)
        table["opacity_logits"][:20] = -12.0  # below 1/255: not rendered
    return trainer


def _posed(trainer, frame, **kw):
    model = trainer.model
    body = trainer.body_state(frame)
    camera = Camera3.from_camera(frame.camera)
    return model.pose(body, model.time_axis(frame.time) + 0.01, camera.center, **kw), camera


def test_pose_with_kernels_matches_the_torch_path_in_values_and_gradients(trained, tiny_frames):
    frame = tiny_frames[3]
    params = list(trained.model.parameters()) + [trained.pose_deltas]
    results = []
    for reference in (True, False):
        for p in params:
            p.grad = None
        if reference:
            with kernels.reference():
                posed, _ = _posed(trained, frame, sh_degree=1)
        else:
            posed, _ = _posed(trained, frame, sh_degree=1)
        gen = torch.Generator().manual_seed(0)
        loss = sum(
            (t * torch.randn(t.shape, generator=gen)).sum() for t in (posed.means, posed.quats, posed.colors)
        )
        loss.backward()
        grads = {
            name: p.grad.clone()
            for name, p in [*trained.model.named_parameters(), ("pose_deltas", trained.pose_deltas)]
            if p.grad is not None
        }
        results.append((posed, grads))
    (ref, ref_grads), (fast, fast_grads) = results
    assert torch.equal(ref.index, fast.index) and ref.index.numel() < trained.model.table.num
    for name in ("means", "quats", "colors", "opacities", "scales"):
        torch.testing.assert_close(getattr(fast, name), getattr(ref, name), atol=2e-5, rtol=1e-4)
    assert set(fast_grads) == set(ref_grads)
    for name, want in ref_grads.items():
        scale = max(float(want.abs().max()), 1e-6)
        torch.testing.assert_close(fast_grads[name], want, atol=2e-4 * scale, rtol=1e-3, msg=name)


def test_culling_before_colour_changes_no_pixel(trained, tiny_frames):
    """A close-up camera sees a part of the body: the rows it cannot see are dropped before
    colour, and the image is the one rendered from every row."""
    frame = tiny_frames[2]
    camera = Camera3.from_camera(frame.camera)
    camera.K = camera.K.clone()
    camera.K[0, 0] *= 4.0  # zoomed in four times on the image centre
    camera.K[1, 1] *= 4.0
    model = trained.model
    body = trained.body_state(frame)
    u = model.time_axis(frame.time)
    with torch.no_grad():
        everything = model.pose(body, u, camera.center)
        culled = model.pose(body, u, camera.center, camera=camera)
        full_image, full_alpha, info = render(everything, camera, background=0.0)
        image, alpha, _ = render(culled, camera, background=0.0)
    kept = culled.means.shape[0]
    assert kept < 0.8 * everything.means.shape[0]  # most of the body is out of view
    assert kept >= int(info["visible"].sum())  # never fewer than the rasterizer draws
    torch.testing.assert_close(image, full_image, atol=1e-6, rtol=0)
    torch.testing.assert_close(alpha, full_alpha, atol=1e-6, rtol=0)


def test_colour_cache_refreshes_in_turns_and_catches_up(trained, tiny_frames):
    model = trained.model
    frames = tiny_frames[:6]
    cache = ColorCache(refresh_every=3)
    with torch.no_grad():
        first, _ = _posed(trained, frames[0], color_cache=cache)
        assert cache.evaluated == first.colors.shape[0]  # a fresh cache evaluates everything
        for frame in frames[1:4]:
            cached, _ = _posed(trained, frame, color_cache=cache)
            exact, _ = _posed(trained, frame)
            rows = cached.colors.shape[0]
            assert abs(cache.evaluated - rows / 3) <= rows / 3 * 0.1 + 2
            assert not torch.equal(cached.colors, exact.colors)  # two thirds are a frame or two old
        # the same pose three frames in a row: every row has been refreshed for it
        for _ in range(3):
            cached, _ = _posed(trained, frames[5], color_cache=cache)
        exact, _ = _posed(trained, frames[5])
        torch.testing.assert_close(cached.colors, exact.colors)
        one = ColorCache(refresh_every=1)
        again, _ = _posed(trained, frames[1], color_cache=one)
        torch.testing.assert_close(again.colors, _posed(trained, frames[1])[0].colors)
    with torch.no_grad():
        model.table["features"].add_(0.0)  # an optimiser step: the colours belong to another model now
        _posed(trained, frames[5], color_cache=cache)
    assert cache.evaluated == exact.colors.shape[0]


def test_renderer_streams_are_exact_at_refresh_one_and_close_otherwise(trained, tiny_frames):
    exact = AvatarRenderer(trained.model)
    streamed = AvatarRenderer(trained.model, color_refresh_every=2)
    worst = 0
    for frame in tiny_frames[:6]:
        a = exact.render(frame.camera, frame.smpl, frame.time).image.astype(int)
        b = streamed.render(frame.camera, frame.smpl, frame.time, stream="live").image.astype(int)
        c = streamed.render(frame.camera, frame.smpl, frame.time).image.astype(int)  # no stream: exact
        assert np.array_equal(a, c)
        worst = max(worst, int(np.abs(a - b).max()))
    assert worst <= 8  # colours at most one frame old (8-bit levels)
    with pytest.raises(ValueError, match="color_refresh_every"):
        AvatarRenderer(trained.model, color_refresh_every=0)


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)) / 255.0**2
    return -10 * math.log10(max(mse, 1e-12))


def _held_out_psnr(trainer, tiny_synth) -> float:
    from stg_node.avatar.data_spec import DataSpec

    views = DataSpec(str(tiny_synth), "synthetic", size=128).open("novel_view")
    renderer = AvatarRenderer(trainer.model)
    scores = []
    for sample in views:
        truth = np.where(sample.mask[..., None] > 127, sample.image, 0).astype(np.uint8)
        scores.append(_psnr(renderer.render(sample.camera, sample.smpl, sample.time).image, truth))
    return float(np.mean(scores))


def test_training_with_the_kernels_scores_like_the_torch_path(tiny_frames, tiny_synth):
    """Same seed and schedule (200 steps, densification, flow, pose refinement): the model trained
    with the fused kernels scores within 0.1 dB of the one trained with torch on held-out views."""
    config = small_config(iterations=200)
    scores = {}
    for name in ("torch", "kernels"):
        trainer = Trainer(config, seed=0)
        trainer.add_frames(tiny_frames)
        if name == "torch":
            with kernels.reference():
                for _ in range(config.iterations):
                    assert not trainer.step().skipped
                scores[name] = _held_out_psnr(trainer, tiny_synth)
        else:
            for _ in range(config.iterations):
                assert not trainer.step().skipped
            scores[name] = _held_out_psnr(trainer, tiny_synth)
    assert scores["torch"] > 18.0
    assert abs(scores["kernels"] - scores["torch"]) <= 0.1, scores


def test_a_cache_fed_by_another_model_starts_afresh_even_at_a_freed_models_address(trained, tiny_frames):
    """The cache key names the model by a token the key itself holds, not id(): a model freed and
    another built in its place (a hot swap) may get the same id, and with the same version
    counters its colours were taken for the old model's. Copies get tokens of their own."""
    import copy
    import gc

    frame = tiny_frames[0]
    body = trained.body_state(frame)
    center = Camera3.from_camera(frame.camera).center
    cache = ColorCache(refresh_every=3)
    for scale in (1.0, 1.5, 2.0, 2.5):  # each model: the same number of edits, other weights
        model = copy.deepcopy(trained.model)
        with torch.no_grad():
            for p in model.color_mlp.parameters():
                p.mul_(scale)
            posed = model.pose(body, 0.01, center, color_cache=cache)
            exact = model.pose(body, 0.01, center)
        assert cache.evaluated == posed.colors.shape[0]  # a new model: every colour evaluated
        torch.testing.assert_close(posed.colors, exact.colors)
        del model, posed, exact
        gc.collect()  # the next copy may take this one's address
