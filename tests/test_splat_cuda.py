"""The gsplat (CUDA) backend: against the CPU kernels on the same scenes (`gpu` tests: need a
GPU and the `cuda` extra, skipped cleanly otherwise), and the wrapper's plumbing (info,
means2d .grad/.absgrad hooks, depth, background) against a stand-in for gsplat built on the
torch reference, which runs everywhere."""

from __future__ import annotations

import logging
import sys
import time
import types

import pytest
import torch

from stg_node.splat import api, cuda_backend, rasterize, torch_reference
from stg_node.splat.api import cpu_backend_status, cuda_backend_status
from stg_node.splat.scenes import random_scene


@pytest.fixture
def gsplat_here():
    status = cuda_backend_status()
    if status is not None:
        pytest.skip(f"cuda backend unavailable: {status}")


def _render(backend, device, scene, viewmat, K, width, height, **options):
    params = [t.to(device).clone().requires_grad_(True) for t in scene.params()]
    image, alpha, info = rasterize(
        *params, viewmat.to(device), K.to(device), width, height, backend=backend, **options
    )
    gen = torch.Generator().manual_seed(0)
    weights = torch.rand(image.shape, generator=gen).to(device)
    loss = (image * weights).sum() + alpha.sum() * 0.5
    if "depth" in info:
        loss = loss + 0.01 * info["depth"].sum()
    loss.backward()
    out = {"image": image.detach().cpu().double(), "alpha": alpha.detach().cpu().double()}
    if "depth" in info:
        out["depth"] = info["depth"].detach().cpu().double()
    grads = {i: p.grad.cpu().double() for i, p in enumerate(params)}
    grads["means2d"] = info["means2d"].grad.cpu().double()
    grads["absgrad"] = info["means2d"].absgrad.cpu().double()
    return out, grads, info


@pytest.mark.gpu
@pytest.mark.parametrize(
    "options",
    [{}, {"antialiased": True}, {"render_depth": True}, {"background": torch.tensor([0.2, 0.3, 0.4])}],
)
def test_cuda_matches_cpu(options, gsplat_here):
    """The same model renders the same on gsplat and on our kernels: same constants (alpha clamp
    0.999, 1/255, T stop 1e-4), same culling rules, so the same visible set.

    Tolerances (docs/SPLAT.md, "Where the backends differ"): gsplat projects in float32 with
    fast math, we in float64, so a radius can round differently when extent * sigma lies within
    ~1e-5 of an integer, and a visible flag can flip only when a box edge lies within float32
    rounding of the image border: expected well under one Gaussian in 2000, allowed 2. Images:
    measured MAE 4e-8 on an H100; 1e-4 leaves room for a pixel whose transmittance stop flips
    under rounding. Gradients: measured 6e-6 relative; allowed 1e-3."""
    reference = "cpu" if cpu_backend_status() is None else "torch"
    # Opacities up to 1: the alpha clamp and the transmittance stop are exercised.
    scene, viewmat, K = random_scene(2000, 128, 96, seed=4, max_opacity=1.0)
    cuda_opts = dict(options)
    if "background" in cuda_opts:
        cuda_opts["background"] = cuda_opts["background"].cuda()
    out_g, grad_g, info_g = _render("cuda", "cuda", scene, viewmat, K, 128, 96, **cuda_opts)
    out_c, grad_c, info_c = _render(reference, "cpu", scene, viewmat, K, 128, 96, **options)
    assert info_g["backend"] == "cuda"
    assert float(out_c["alpha"].mean()) > 0.3 and float((out_c["alpha"] > 0.99).float().mean()) > 0.01
    for key in out_c:
        mae = float((out_g[key] - out_c[key]).abs().mean())
        assert mae < 1e-4, f"{key}: MAE {mae}"
    vis_g, vis_c = info_g["visible"].cpu(), info_c["visible"]
    assert int(vis_c.sum()) > 1000
    assert int((vis_g != vis_c).sum()) <= 2
    both = vis_g & vis_c
    radii_diff = (info_g["radii"].cpu()[both] - info_c["radii"][both]).abs()
    assert int(radii_diff.max()) <= 1 and float((radii_diff == 0).float().mean()) > 0.995
    for key in grad_c:
        rel = float((grad_g[key] - grad_c[key]).norm() / grad_c[key].norm())
        assert rel < 1e-3, f"gradient {key}: relative error {rel}"


@pytest.mark.gpu
def test_empty_scenes_on_the_gpu_render_the_background(gsplat_here):
    """No Gaussians (gsplat 1.5.3 would abort the process), all culled, zero-area images."""
    scene, viewmat, K = random_scene(50, 32, 24, seed=3)
    bg = torch.tensor([0.1, 0.2, 0.3], device="cuda")
    params = [t.cuda() for t in scene.params()]
    for n, width, height in [(0, 32, 24), (50, 0, 24), (50, 32, 0)]:
        ps = [p[:n].clone().requires_grad_(True) for p in params]
        image, alpha, info = rasterize(
            *ps, viewmat.cuda(), K.cuda(), width, height, background=bg, backend="cuda"
        )
        assert image.shape == (height, width, 3) and alpha.shape == (height, width, 1)
        assert torch.equal(image, bg.expand_as(image)) and not info["visible"].any()
        (image.sum() + alpha.sum()).backward()
        assert all(p.grad is not None and not p.grad.any() for p in ps)


@pytest.mark.gpu
def test_auto_uses_gsplat_for_cuda_tensors(gsplat_here):
    scene, viewmat, K = random_scene(100, 32, 32, seed=1)
    params = [t.cuda() for t in scene.params()]
    _, _, info = rasterize(*params, viewmat.cuda(), K.cuda(), 32, 32)
    assert info["backend"] == "cuda"
    assert info["means2d"].shape == (100, 2) and info["radii"].shape == (100, 2)


class _WouldCrash(AssertionError):
    """What the real gsplat does here is take the process down or compute NaN."""


class _FakeGsplat:
    """gsplat 1.5.3's ``rasterization`` contract for one camera and packed=False, on the torch
    reference: radii [C, N, 2]; means2d [C, N, 2] (a non-leaf) whose .absgrad its backward sets;
    culled rows left unwritten (here: filled with junk); render modes RGB / RGB+D / RGB+ED;
    backgrounds. It refuses, loudly, what would kill the real one: 0 Gaussians or a zero-area
    image (an integer division by zero in its kernel launchers: SIGFPE) and a zero quaternion
    (rsqrt(0) -> NaN covariance)."""

    __version__ = "1.5.3"
    calls: list = []

    class _BaseAbsGrad:
        def __init__(self, base):
            self.base = base

        def add_absgrad(self, index, values):
            if getattr(self.base, "absgrad", None) is None:
                self.base.absgrad = torch.zeros_like(self.base)
            self.base.absgrad[0].index_add_(0, index, values)

    @classmethod
    def rasterization(
        cls,
        means,
        quats,
        scales,
        opacities,
        colors,
        viewmats,
        Ks,
        width,
        height,
        near_plane=0.01,
        far_plane=1e10,
        radius_clip=0.0,
        eps2d=0.3,
        packed=True,
        tile_size=16,
        backgrounds=None,
        render_mode="RGB",
        absgrad=False,
        rasterize_mode="classic",
    ):
        if means.shape[0] == 0 or width * height == 0:
            raise _WouldCrash("gsplat 1.5.3 divides by N or by H * W here: Floating point exception")
        if bool((quats.norm(dim=-1) == 0).any()):
            raise _WouldCrash("a zero quaternion reached gsplat (NaN covariance)")
        assert means.dtype == torch.float32 and colors.dtype == torch.float32
        cls.calls.append(
            dict(
                packed=packed,
                tile_size=tile_size,
                render_mode=render_mode,
                absgrad=absgrad,
                rasterize_mode=rasterize_mode,
                viewmats=tuple(viewmats.shape),
                Ks=tuple(Ks.shape),
                backgrounds=backgrounds,
            )
        )
        proj = torch_reference.project(
            means,
            quats,
            scales,
            opacities,
            viewmats[0],
            Ks[0],
            width,
            height,
            near_plane=near_plane,
            far_plane=far_plane,
            eps2d=eps2d,
            radius_clip=radius_clip,
            antialiased=rasterize_mode == "antialiased",
        )
        vis = proj.visible
        junk = 123.0  # gsplat's outputs are torch.empty: culled rows hold whatever was there
        base = torch.where(vis[:, None], proj.means2d, junk)[None] * 1.0  # a non-leaf [1, N, 2]
        proj.means2d = base[0]
        holder = cls._BaseAbsGrad(base) if absgrad else None
        if render_mode.startswith("RGB+"):
            colors = torch.cat([colors, proj.depths[:, None]], dim=1)
        image, alpha = torch_reference.rasterize(proj, colors, width, height, holder=holder)
        if backgrounds is not None:
            bg = torch.cat([backgrounds[0], torch.zeros(colors.shape[1] - backgrounds.shape[1])])
            image = image + (1 - alpha) * bg
        if render_mode == "RGB+ED":
            image = torch.cat([image[..., :-1], image[..., -1:] / alpha.clamp(min=1e-10)], dim=-1)
        meta = {
            "means2d": base,
            "radii": proj.radii[None],
            "depths": torch.where(vis, proj.depths, junk)[None],
            "conics": torch.where(vis[:, None], proj.conics, junk)[None],
            "opacities": torch.where(vis, proj.opacities, junk)[None],
            "isect_ids": torch.zeros(torch_reference.count_intersections(proj)),
        }
        return image[None], alpha[None], meta


@pytest.fixture
def stand_in(monkeypatch):
    """The cuda backend wired to `_FakeGsplat` and serving CPU tensors, behind the public API."""
    monkeypatch.setattr(cuda_backend, "import_gsplat", lambda: _FakeGsplat)
    monkeypatch.setattr(cuda_backend, "ensure_kernels", lambda: None)
    fake = cuda_backend.CudaBackend()
    fake.device_type = "cpu"
    fake.check = lambda: None
    real = api.backend_impl
    monkeypatch.setattr(api, "backend_impl", lambda name: fake if name == "cuda" else real(name))
    _FakeGsplat.calls.clear()
    return _FakeGsplat


@pytest.mark.parametrize(
    "options",
    [
        {},
        {"render_depth": True, "antialiased": True},
        {"render_depth": True, "depth_mode": "accumulated"},
        {"background": torch.tensor([0.2, 0.3, 0.4])},
    ],
)
def test_gsplat_wrapper_plumbing_with_a_stand_in(stand_in, options):
    """Everything our wrapper and the api do around gsplat, checked against the torch backend:
    outputs, info, and info["means2d"].grad / .absgrad when the loss also uses means2d."""
    scene, viewmat, K = random_scene(300, 48, 40, seed=2)
    results = {}
    for name in ("cuda", "torch"):
        params = [t.clone().requires_grad_(True) for t in scene.params()]
        image, alpha, info = rasterize(*params, viewmat, K, 48, 40, backend=name, **options)
        loss = (image * torch.linspace(0, 1, 48)[None, :, None]).sum() + alpha.sum()
        loss = loss + (info["means2d"] ** 2).sum() * 1e-4  # a second, direct use of means2d
        if "depth" in info:
            loss = loss + info["depth"].sum() * 0.01
        loss.backward()
        results[name] = (image.detach(), alpha.detach(), info, [p.grad for p in params])
    (img_w, a_w, info_w, g_w), (img_t, a_t, info_t, g_t) = results["cuda"], results["torch"]
    call = stand_in.calls[-1]
    assert call["packed"] is False and call["tile_size"] == 16 and call["backgrounds"] is None
    assert call["viewmats"] == (1, 4, 4) and call["Ks"] == (1, 3, 3) and call["absgrad"]
    assert call["render_mode"] == ("RGB+D" if options.get("render_depth") else "RGB")
    assert info_w["backend"] == "cuda"
    assert torch.allclose(img_w, img_t, atol=1e-6) and torch.allclose(a_w, a_t, atol=1e-6)
    if "depth" in info_t:
        assert torch.allclose(info_w["depth"], info_t["depth"], atol=1e-5)
    assert info_w["radii"].shape == (300, 2) and torch.equal(info_w["visible"], info_t["visible"])
    assert torch.equal(info_w["radii"], info_t["radii"])
    for key in ("depths", "conics", "opacities"):  # gsplat's unwritten rows come back as zeros
        assert torch.equal(info_w[key].detach(), info_t[key].detach()), key
    assert info_w["n_intersections"] == info_t["n_intersections"]
    for a, b in zip(g_w, g_t, strict=True):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-6)
    assert torch.allclose(info_w["means2d"].grad, info_t["means2d"].grad, rtol=1e-4, atol=1e-6)
    assert torch.allclose(info_w["means2d"].absgrad, info_t["means2d"].absgrad, rtol=1e-4, atol=1e-6)


def test_empty_scenes_and_zero_quaternions_never_reach_gsplat(stand_in):
    """No Gaussians and zero-area images are answered by the api layer (the stand-in raises
    where gsplat would kill the process); a zero quaternion reaches it as the identity."""
    scene, viewmat, K = random_scene(40, 32, 24, seed=5)
    bg = torch.tensor([0.1, 0.2, 0.3])
    for n, width, height in [(0, 32, 24), (40, 0, 24), (40, 32, 0), (0, 0, 0)]:
        params = [t[:n].clone().requires_grad_(True) for t in scene.params()]
        image, alpha, info = rasterize(*params, viewmat, K, width, height, background=bg, backend="cuda")
        assert image.shape == (height, width, 3) and torch.equal(image, bg.expand_as(image))
        assert info["backend"] == "cuda" and info["n_intersections"] == 0
        (image.sum() + alpha.sum() + info["means2d"].sum()).backward()
        assert all(p.grad is not None and not p.grad.any() for p in params)
        assert info["means2d"].absgrad.shape == (n, 2)
    assert stand_in.calls == []
    quats = scene.quats.clone()
    quats[::3] = 0.0
    identity = quats.clone()
    identity[::3] = torch.tensor([1.0, 0.0, 0.0, 0.0])
    params = list(scene.params())
    zero_img, _, _ = rasterize(params[0], quats, *params[2:], viewmat, K, 32, 24, backend="cuda")
    id_img, _, _ = rasterize(params[0], identity, *params[2:], viewmat, K, 32, 24, backend="cuda")
    assert len(stand_in.calls) == 2 and torch.equal(zero_img, id_img)


def test_old_gsplat_is_refused_and_auto_falls_back(monkeypatch):
    class Old:
        __version__ = "1.4.0"

    monkeypatch.setitem(sys.modules, "gsplat", Old)
    with pytest.raises(cuda_backend.GsplatUnavailable, match=r"gsplat 1\.4\.0 is older than 1\.5\.3"):
        cuda_backend.import_gsplat()


def test_first_use_build_is_announced_with_progress(monkeypatch, caplog, capsys):
    """gsplat's JIT build (minutes on first use): a warning naming the cache and the prebuild
    command, an elapsed-time bar while it runs; a missing toolkit is a clear error."""
    monkeypatch.setattr(cuda_backend, "import_gsplat", lambda: _FakeGsplat)
    monkeypatch.setattr(cuda_backend, "kernels_built", lambda: False)
    monkeypatch.setattr(cuda_backend, "_kernels_ready", False)

    def slow_build():
        time.sleep(1.2)
        return types.SimpleNamespace(_C=object())

    monkeypatch.setattr(cuda_backend, "_load_gsplat_kernels", slow_build)
    with caplog.at_level(logging.WARNING, logger="stg_node.splat.cuda_backend"):
        cuda_backend.ensure_kernels()
        cuda_backend.ensure_kernels()  # once per process
    messages = [r.getMessage() for r in caplog.records]
    assert len(messages) == 2, messages
    assert "building gsplat's CUDA kernels" in messages[0] and "stg-splat-prebuild" in messages[0]
    assert str(cuda_backend.gsplat_build_dir()) in messages[0]
    assert "building gsplat CUDA kernels: 00:0" in capsys.readouterr().err

    monkeypatch.setattr(cuda_backend, "_kernels_ready", False)
    monkeypatch.setattr(cuda_backend, "_load_gsplat_kernels", lambda: types.SimpleNamespace(_C=None))
    with pytest.raises(cuda_backend.GsplatUnavailable, match="no CUDA toolkit"):
        cuda_backend.ensure_kernels()
    monkeypatch.setattr(cuda_backend, "_load_gsplat_kernels", lambda: 1 / 0)
    with pytest.raises(cuda_backend.GsplatUnavailable, match="failed to build or load"):
        cuda_backend.ensure_kernels()


def test_a_failing_gsplat_build_falls_back_under_auto(stand_in, monkeypatch):
    """auto: a build that fails at the first render is remembered, warned about once, and the
    torch reference renders; naming the backend raises."""
    scene, viewmat, K = random_scene(30, 16, 16, seed=1)

    def broken():
        raise cuda_backend.GsplatUnavailable("nvcc exploded (test)")

    monkeypatch.setattr(cuda_backend, "ensure_kernels", broken)
    monkeypatch.setattr(api, "_failures", {})
    monkeypatch.setattr(api, "_warned", set())
    with pytest.raises(cuda_backend.GsplatUnavailable, match="nvcc exploded"):
        rasterize(*scene.params(), viewmat, K, 16, 16, backend="cuda")
    fake = api.backend_impl("cuda")
    monkeypatch.setattr(fake, "device_type", "cpu")
    real_resolve = api.resolve_backend
    monkeypatch.setattr(api, "resolve_backend", lambda b, d: "cuda" if b == "auto" else real_resolve(b, d))
    with pytest.warns(RuntimeWarning, match="nvcc exploded"):
        _, _, info = rasterize(*scene.params(), viewmat, K, 16, 16)
    assert info["backend"] == "torch"
    assert "nvcc exploded" in api.cuda_backend_status()
