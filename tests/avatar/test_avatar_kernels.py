"""The avatar's fast paths against today's torch path: the fused kernels inside AvatarModel.pose
(values and gradients), culling before colour, the per-stream colour cache, and a training run
with the kernels scoring like one with the torch reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from avatar_helpers import small_config, trained_held_out_psnr

from stg_node.avatar import kernels
from stg_node.avatar.color_cache import ColorCache
from stg_node.avatar.model import Camera3, render
from stg_node.avatar.renderer import AvatarRenderer
from stg_node.avatar.trainer import Trainer

pytestmark = pytest.mark.usefixtures("cpu_kernels")  # skips where the kernels cannot build


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


def test_the_next_frames_centres_in_the_pose_pass_match_posed_means(trained, tiny_frames):
    """AvatarModel.pose's next_frame (the flow loss's next frame, skinned in the pose's own kernel
    pass): the centres posed_means gives for the same rows (moving rows carry their own offsets at
    the next time), with the kernels and with the torch path, and the gradients of a loss over both
    frames' centres and the orientations the same either way."""
    frame, nxt = tiny_frames[3], tiny_frames[4]
    model = trained.model
    camera = Camera3.from_camera(frame.camera)
    u, u_next = model.time_axis(frame.time) + 0.01, model.time_axis(nxt.time) + 0.01
    params = list(model.parameters()) + [trained.pose_deltas]
    results = []
    for reference in (True, False):
        for p in params:
            p.grad = None
        with kernels.reference() if reference else _no_block():
            body, next_body = trained.body_state(frame), trained.body_state(nxt)
            next_bones, next_state = model.bones(next_body), model.spacetime(u_next)
            assert next_state.offsets is not None  # the moving rows' own centres at the next time
            posed = model.pose(body, u, camera.center, camera=camera, next_frame=(next_bones, next_state))
            with torch.no_grad():
                want = model.posed_means(next_bones, u_next, state=next_state)[posed.index]
        torch.testing.assert_close(posed.next_means.detach(), want, atol=2e-6, rtol=1e-5)
        gen = torch.Generator().manual_seed(1)
        loss = sum(
            (t * torch.randn(t.shape, generator=gen)).sum()
            for t in (posed.means, posed.quats, posed.next_means)
        )
        loss.backward()
        results.append(
            {
                n: p.grad.clone()
                for n, p in [*model.named_parameters(), ("pose", trained.pose_deltas)]
                if p.grad is not None
            }
        )
    ref_grads, fast_grads = results
    assert set(fast_grads) == set(ref_grads) and "table.params.skin_delta" in ref_grads
    for name, want in ref_grads.items():
        scale = max(float(want.abs().max()), 1e-6)
        torch.testing.assert_close(fast_grads[name], want, atol=2e-4 * scale, rtol=1e-3, msg=name)


def _no_block():
    import contextlib

    return contextlib.nullcontext()


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


def test_training_with_the_kernels_scores_like_the_torch_path(tiny_frames, tiny_synth):
    """Same seed and schedule (200 steps, densification, flow, pose refinement): the model trained
    with the fused kernels scores within 0.1 dB of the one trained with torch on held-out views."""
    config = small_config(iterations=200)
    with kernels.reference():
        scores = {"torch": trained_held_out_psnr(tiny_frames, tiny_synth, config)}
    scores["kernels"] = trained_held_out_psnr(tiny_frames, tiny_synth, config)
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


@pytest.mark.parametrize("shape", [(5, 7), (700, 600, 3), (3, 1)])
def test_image_conversion_in_slices_gives_the_rounded_clamped_levels_and_leaves_its_input(shape):
    """renderer._to_uint8 converts cache-sized slices; the levels are numpy's round-half-up of the
    clamped values over the whole array, across slice borders (700x600x3 spans five slices)."""
    from stg_node.avatar.renderer import _to_uint8

    gen = torch.Generator().manual_seed(1)
    values = torch.rand(shape, generator=gen) * 1.4 - 0.2  # out of range on both sides
    edges = torch.tensor([0.5 / 255, 1.5 / 255 - 1e-6, 1.0, 0.0])[: values.numel()]
    values.view(-1)[: edges.numel()] = edges
    before = values.clone()
    scaled = values.numpy() * np.float32(255.0) + np.float32(0.5)  # float32 steps, as the renderer
    want = np.floor(np.clip(scaled, 0.0, 255.0)).astype(np.uint8)
    got = _to_uint8(values)
    assert got.dtype == np.uint8 and got.shape == shape
    assert np.array_equal(got, want)
    assert torch.equal(values, before)


def _pose_both_ways(model, body, u, camera):
    """Posed without gradient (the renderer's path: moving rows kept between frames) and with the
    spacetime terms of every row evaluated densely and handed in (the reference)."""
    with torch.no_grad():
        fast = model.pose(body, u, camera.center, camera=camera)
        dense = model.spacetime(u)
        ref = model.pose(body, u, camera.center, camera=camera, state=dense)
    return fast, ref


def _assert_same_posed(fast, ref, exact: bool):
    assert (fast.index is None) == (ref.index is None)
    if fast.index is not None:
        assert torch.equal(fast.index, ref.index)
    for name in ("means", "quats", "scales", "opacities", "colors", "canonical"):
        a, b = getattr(fast, name), getattr(ref, name)
        if exact:
            assert torch.equal(a, b), name
        else:  # the moving rows' terms on a gathered subset: the same maths, float rounding apart
            torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-6, msg=name)


def test_render_pose_evaluates_only_moving_rows_and_matches_the_dense_terms(trained, tiny_frames):
    import copy

    from stg_node.avatar import spacetime

    model = copy.deepcopy(trained.model).eval()
    frame = tiny_frames[4]
    camera = Camera3.from_camera(frame.camera)
    body = trained.body_state(frame)
    u = model.time_axis(frame.time) + 0.01
    table = model.table
    gen = torch.Generator().manual_seed(5)
    with torch.no_grad():  # a few finite temporal windows around u (temporal opacity below 1)
        windowed = torch.rand(table.num, generator=gen) < 0.2
        table["t_log_scale"][windowed] = math.log(0.5)
        table["t_center"][windowed] = u + 0.3 * torch.randn(int(windowed.sum()), generator=gen)
    moving = int(table.motion_active().sum())
    assert 0 < moving < table.num // 2  # the subset path
    fast, ref = _pose_both_ways(model, body, u, camera)
    assert not torch.equal(fast.canonical, model.table["means"][fast.index])  # offsets applied
    assert float(fast.opacities.min()) < 0.5 * float(ref.opacities.max())  # temporal factors applied
    _assert_same_posed(fast, ref, exact=False)
    with torch.no_grad():
        image, alpha, _ = render(fast, camera, background=0.0)
        ref_image, ref_alpha, _ = render(ref, camera, background=0.0)
    torch.testing.assert_close(image, ref_image, atol=1e-5, rtol=0)
    torch.testing.assert_close(alpha, ref_alpha, atol=1e-5, rtol=0)
    # the kept rows follow edits of the table: most rows moving (the dense path, bit for bit) ...
    with torch.no_grad():
        table["motion"][: 3 * table.num // 4] = 0.01
    _assert_same_posed(*_pose_both_ways(model, body, u, camera), exact=True)
    # ... and nothing moving, every window persistent: the rigid part alone, bit for bit
    with torch.no_grad():
        for name in ("motion", "rot_motion"):
            table[name].zero_()
        table["t_log_scale"].fill_(math.log(2 * spacetime.PERSISTENT_SCALE))
    fast, ref = _pose_both_ways(model, body, u, camera)
    with torch.no_grad():
        assert model._render_spacetime(u, False).offsets is None
    _assert_same_posed(fast, ref, exact=True)


def test_colour_input_encoding_is_the_closed_form():
    from stg_node.avatar.color import encoded_inputs, positional_encoding

    gen = torch.Generator().manual_seed(0)
    x = torch.rand(50, 3, generator=gen) * 2 - 1
    rest = torch.randn(50, 7, generator=gen)
    columns = [x[:, i] for i in range(3)]
    for fn in (np.sin, np.cos):
        columns += [
            torch.as_tensor(fn(2.0**k * np.pi * x[:, i].double().numpy())) for i in range(3) for k in range(4)
        ]
    want = torch.stack([c.float() for c in columns], dim=1)
    torch.testing.assert_close(positional_encoding(x, 4), want, atol=2e-6, rtol=0)
    assert torch.equal(encoded_inputs(x, 4, rest), torch.cat([positional_encoding(x, 4), rest], dim=1))
    assert torch.equal(encoded_inputs(x, 0, rest), torch.cat([x, rest], dim=1))


def _encoding_by_autograd(x, freqs, *rest):
    """The colour input built from plain torch ops (autograd differentiates every one)."""
    scales = (2.0 ** torch.arange(freqs, dtype=x.dtype)) * np.pi
    angles = (x[..., None] * scales).flatten(-2)
    return torch.cat([x, torch.sin(angles), torch.cos(angles), *rest], dim=-1)


def test_colour_input_encoding_gradients_match_autograd_in_float64():
    """The training step's encoding (its own backward, reusing the forward's sines and cosines):
    values equal to plain ops, gradients of x and of the passed-through columns equal to autograd
    through plain ops in float64 and to finite differences (gradcheck); a column without gradient
    gets none."""
    from stg_node.avatar.color import encoded_inputs

    gen = torch.Generator().manual_seed(1)
    x = (torch.rand(40, 3, generator=gen, dtype=torch.float64) * 2 - 1).requires_grad_(True)
    feat = torch.randn(40, 5, generator=gen, dtype=torch.float64).requires_grad_(True)
    basis = torch.randn(40, 4, generator=gen, dtype=torch.float64)  # no gradient (view directions)
    out = encoded_inputs(x, 4, feat, basis)
    assert out.grad_fn is not None and "EncodedInputs" in type(out.grad_fn).__name__
    want = _encoding_by_autograd(x, 4, feat, basis)
    assert torch.equal(out, want)
    g = torch.randn(out.shape, generator=gen, dtype=torch.float64)
    got = torch.autograd.grad(out, (x, feat), g)
    ref = torch.autograd.grad(want, (x, feat), g)
    for a, b in zip(got, ref, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    x6, f6 = x[:6].detach().requires_grad_(True), feat[:6].detach().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, f: encoded_inputs(a, 3, f, basis[:6]), (x6, f6))
    only_x = encoded_inputs(x, 2, basis)  # the trailing column block needs no gradient
    (gx,) = torch.autograd.grad(only_x, (x,), torch.ones_like(only_x))
    (gx_ref,) = torch.autograd.grad(_encoding_by_autograd(x, 2, basis), (x,), torch.ones_like(only_x))
    torch.testing.assert_close(gx, gx_ref, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize(
    "preset_name, active", [("balanced", 1), ("quality", 1), ("quality", 2), ("fast", 0)]
)
def test_colour_mlp_kernel_is_its_torch_path(preset_name, active):
    """ColorMLP on the kernel (gamma(x) and SH(d) built inside it) against its torch path
    (kernels.reference()): colours and the gradients of centres, features, directions, pose code and
    every weight; bands not switched on yet (``active`` < the preset's degree) fed as zeros; every
    row, and a turn of the rows read where they lie (their gradients back at their rows)."""
    from stg_node.avatar import preset
    from stg_node.avatar.color import ColorMLP

    cfg = preset(preset_name).model
    torch.manual_seed(3)
    mlp = ColorMLP(cfg, torch.tensor([[-1.0, -1.2, -0.5], [1.0, 0.9, 0.6]]))
    with torch.no_grad():  # a trained network's scale, not the grey start
        mlp.net[-1].weight.mul_(10.0)
    gen = torch.Generator().manual_seed(4)
    n = 150
    inputs = [
        torch.rand(n, 3, generator=gen) * 2 - 1,
        torch.randn(n, cfg.feature_dim, generator=gen),
        torch.randn(1, 207, generator=gen) * 0.3,
        torch.nn.functional.normalize(torch.randn(n, 3, generator=gen), dim=1),
    ]
    turn = torch.randperm(n, generator=gen)[:61]  # a training step's turn of the rows, in no order

    for rows in (None, turn):
        g = torch.randn(n if rows is None else rows.numel(), 3, generator=gen)

        def run(rows=rows, g=g):
            leaves = [t.clone().requires_grad_(True) for t in inputs]
            out = mlp(*leaves, active, rows=rows)
            grads = torch.autograd.grad((out * g).sum(), [*leaves, *mlp.parameters()])
            return out.detach(), grads

        out, grads = run()
        with kernels.reference():
            want, want_grads = run()
        torch.testing.assert_close(out, want, atol=2e-6, rtol=1e-5)
        for got, ref in zip(grads, want_grads, strict=True):
            torch.testing.assert_close(got, ref, atol=2e-5 * max(float(ref.abs().max()), 1.0), rtol=1e-4)
        if active == 0:  # the constant band alone: the directions take no gradient
            assert torch.equal(grads[3], torch.zeros_like(grads[3]))


def test_render_pose_follows_edits_of_the_scales(trained, tiny_frames):
    """A renderer's poses keep the capped scales between frames; an edit of the table (a training
    step, densification) or of the cap is seen by the next pose."""
    import copy
    import dataclasses

    from stg_node.avatar.gaussians import cap_scale_ratio

    model = copy.deepcopy(trained.model).eval()
    model.config = dataclasses.replace(model.config, joint_shrink=False)
    frame = tiny_frames[1]
    body = trained.body_state(frame)
    center = Camera3.from_camera(frame.camera).center

    def posed_scales():
        with torch.no_grad():
            return model.pose(body, 0.0, center, cull_transparent=False).scales

    first = posed_scales()
    with torch.no_grad():
        model.table["log_scales"][::3] += 0.5
    second = posed_scales()
    want = cap_scale_ratio(model.table["log_scales"].detach().exp(), model.config.max_scale_ratio)
    assert not torch.equal(first, second) and torch.equal(second, want)
    model.config = dataclasses.replace(model.config, max_scale_ratio=2.0)
    assert torch.equal(posed_scales(), cap_scale_ratio(model.table["log_scales"].detach().exp(), 2.0))
