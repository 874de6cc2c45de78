"""Shading on the avatar's fast paths: the fused kernels against the torch reference for a model
lit by a strong room light, and colour streams (color_cache.py) that carry the albedo from frame
to frame while the light is applied anew every frame (normals turn with the pose)."""

from __future__ import annotations

import contextlib
from collections import OrderedDict

import numpy as np
import pytest
import torch
from avatar_helpers import small_config
from scipy.spatial.transform import Rotation

from stg_node.avatar import kernels
from stg_node.avatar.color_cache import ColorCache
from stg_node.avatar.model import BodyState, Camera3
from stg_node.avatar.renderer import AvatarRenderer
from stg_node.avatar.shading import LightSpec
from stg_node.avatar.trainer import Trainer
from stg_node.body import lbs
from stg_node.splat import build


@pytest.fixture(scope="module")
def lit(tiny_frames):
    """A shaded model after 30 steps, then lit by a strong light from +x and a weaker one from
    above (fixed in the world), with learned weight corrections, moving Gaussians and a few
    transparent rows, so that every path is exercised and shading changes colours visibly.
    Per-Gaussian polynomials (motion_basis=0): their ``motion`` column is set directly."""
    trainer = Trainer(small_config(**{"model.motion_basis": 0}), seed=0)
    trainer.add_frames(tiny_frames)
    for _ in range(30):
        trainer.step()
    model = trainer.model
    assert model.shading is not None  # shading is the default
    table = model.table
    gen = torch.Generator().manual_seed(5)
    with torch.no_grad():
        light = model.shading.light
        light.directions.copy_(torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))
        light.colors.copy_(torch.tensor([[3.0, 2.5, 2.0], [0.5, 0.5, 0.5]]))  # softplus: ~3 and ~1
        light.ambient.fill_(-1.0)  # softplus: 0.31, so the side away from the lights is dark
        table["skin_delta"].copy_(0.3 * torch.randn(table["skin_delta"].shape, generator=gen))
        moving = torch.rand(table.num, generator=gen) < 0.3
        table["motion"][moving] = 0.01 * torch.randn(table["motion"][moving].shape, generator=gen)
        table["opacity_logits"][:20] = -12.0  # below 1/255: culled
    return trainer


def _pose(trainer, frame, body=None, center=None, **kw):
    model = trainer.model
    camera = Camera3.from_camera(frame.camera)
    body = body if body is not None else trainer.body_state(frame)
    center = camera.center if center is None else center
    return model.pose(body, model.time_axis(frame.time) + 0.01, center, **kw)


def test_the_light_changes_the_colours_of_this_model(lit, tiny_frames):
    """What the tests below rest on: under this light the shaded colour is far from the albedo."""
    with torch.no_grad():
        shaded = _pose(lit, tiny_frames[2]).colors
        albedo = _pose(lit, tiny_frames[2], light=LightSpec("albedo")).colors
    assert float((shaded - albedo).abs().max()) > 0.3


def test_kernels_and_torch_agree_on_a_shaded_model_in_values_and_gradients(lit, tiny_frames):
    try:
        build.load_kernels()
    except build.ExtensionUnavailable as exc:  # pragma: no cover - machines without a compiler
        pytest.skip(f"CPU kernels unavailable: {exc}")
    frame = tiny_frames[3]
    model = lit.model
    named = [*model.named_parameters(), ("pose_deltas", lit.pose_deltas)]
    results = []
    for reference in (True, False):
        for _, p in named:
            p.grad = None
        with kernels.reference() if reference else contextlib.nullcontext():
            posed = _pose(lit, frame, sh_degree=1)
        gen = torch.Generator().manual_seed(0)
        loss = sum(
            (t * torch.randn(t.shape, generator=gen)).sum() for t in (posed.means, posed.quats, posed.colors)
        )
        loss.backward()
        results.append((posed, {n: p.grad.clone() for n, p in named if p.grad is not None}))
    (ref, ref_grads), (fast, fast_grads) = results
    assert torch.equal(ref.index, fast.index)
    for name in ("means", "quats", "colors", "opacities", "scales"):
        torch.testing.assert_close(getattr(fast, name), getattr(ref, name), atol=2e-5, rtol=1e-4)
    light_grads = [n for n in ref_grads if n.startswith("shading.")]
    assert light_grads and set(fast_grads) == set(ref_grads)  # the light learns on both paths
    for name, want in ref_grads.items():
        scale = max(float(want.abs().max()), 1e-6)
        torch.testing.assert_close(fast_grads[name], want, atol=2e-4 * scale, rtol=1e-3, msg=name)


def _turned(body: BodyState, center: torch.Tensor, degrees: float):
    """The body and the camera turned together by ``degrees`` about the world's y axis through the
    origin: the camera sees the same body from the same side, but the body faces another way in the
    room, so its albedo (which turns with it) is unchanged and its light (fixed in the room) is not."""
    turn = torch.as_tensor(Rotation.from_euler("y", degrees, degrees=True).as_matrix(), dtype=torch.float32)
    root = turn @ lbs.axis_angle_to_matrix(body.Rh[0])
    Rh = lbs.matrix_to_axis_angle(root[None]).reshape(1, 3)
    return BodyState(body.poses, Rh, body.Th @ turn.T), center @ turn.T, turn


def test_a_colour_stream_keeps_the_albedo_and_shades_every_frame(lit, tiny_frames):
    """Body and camera turn together, frame after frame: each Gaussian's albedo stays what it was,
    and its light changes. A stream recomputing a third of the colours per frame renders exactly
    what a one-shot render does, so the cache holds albedo and the light is applied every frame
    (a cache of lit colours would show the light of one or two frames ago on two thirds of them)."""
    frame = tiny_frames[4]
    body = lit.body_state(frame)
    center = Camera3.from_camera(frame.camera).center
    cache = ColorCache(refresh_every=3)
    with torch.no_grad():
        first = _pose(lit, frame, body, center)
        for k, degrees in enumerate((0.0, 25.0, 50.0, 75.0, 100.0)):
            b, c, turn = _turned(body, center, degrees)
            streamed = _pose(lit, frame, b, c, color_cache=cache)
            exact = _pose(lit, frame, b, c)
            if k == 0:
                assert cache.evaluated == exact.colors.shape[0]  # a fresh stream evaluates everything
            else:
                assert cache.evaluated < 0.4 * exact.colors.shape[0]  # a third of them, in turn
            # the whole body turned as meant
            torch.testing.assert_close(exact.means, first.means @ turn.T, atol=1e-4, rtol=0)
            torch.testing.assert_close(streamed.colors, exact.colors, atol=1e-5, rtol=1e-4)
        # the turn changed the light the surfaces get: the test above could fail
        assert float((exact.colors - first.colors).abs().max()) > 0.3


def test_a_stream_that_refreshes_every_frame_is_the_exact_render(lit, tiny_frames):
    cache = ColorCache(refresh_every=1)
    with torch.no_grad():
        for frame in tiny_frames[:5]:
            streamed = _pose(lit, frame, color_cache=cache).colors
            assert torch.equal(streamed, _pose(lit, frame).colors)


def test_renderer_streams_of_a_shaded_model_are_exact_at_refresh_one_and_close_otherwise(lit, tiny_frames):
    exact = AvatarRenderer(lit.model)
    every_frame = AvatarRenderer(lit.model, color_refresh_every=1)
    streamed = AvatarRenderer(lit.model, color_refresh_every=2)
    albedo = AvatarRenderer(lit.model, light=LightSpec("albedo"))
    worst, lit_vs_albedo = 0, 0
    for frame in tiny_frames[:6]:
        a = exact.render(frame.camera, frame.smpl, frame.time).image.astype(int)
        b = every_frame.render(frame.camera, frame.smpl, frame.time, stream="live").image.astype(int)
        c = streamed.render(frame.camera, frame.smpl, frame.time, stream="live").image.astype(int)
        d = albedo.render(frame.camera, frame.smpl, frame.time).image.astype(int)
        assert np.array_equal(a, b)
        worst = max(worst, int(np.abs(a - c).max()))
        lit_vs_albedo = max(lit_vs_albedo, int(np.abs(a - d).max()))
    assert worst <= 8  # albedo at most one frame old, lit this frame (8-bit levels)
    assert lit_vs_albedo > 40  # the light shows in the images


def test_color_streams_are_a_cpu_economy(monkeypatch):
    """On a GPU a stream renders exactly (no cache): the cache's gathers cost more than the MLP there."""
    renderer = AvatarRenderer.__new__(AvatarRenderer)  # the cache rule needs no model
    renderer.color_refresh_every = 3
    renderer._streams = OrderedDict()
    monkeypatch.setattr(AvatarRenderer, "device", property(lambda self: torch.device("cpu")))
    assert isinstance(renderer._color_cache("live"), ColorCache)
    assert renderer._color_cache(None) is None
    monkeypatch.setattr(AvatarRenderer, "device", property(lambda self: torch.device("cuda")))
    assert renderer._color_cache("live") is None
