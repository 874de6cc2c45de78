"""The gsplat (CUDA) backend: against the CPU kernels on the same scenes (`gpu` tests: need a
GPU and the `cuda` extra, skipped cleanly otherwise), and the wrapper's plumbing (info,
means2d .grad/.absgrad hooks, depth, background) against a stand-in for gsplat built on the
torch reference, which runs everywhere."""

from __future__ import annotations

import pytest
import torch

from stg_node.splat import cuda_backend, rasterize, torch_reference
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
    reference = "cpu" if cpu_backend_status() is None else "torch"
    # Opacities below 0.99 / ALPHA_MAX: gsplat versions differ in their alpha clamp.
    scene, viewmat, K = random_scene(2000, 128, 96, seed=4, max_opacity=0.9)
    cuda_opts = dict(options)
    if "background" in cuda_opts:
        cuda_opts["background"] = cuda_opts["background"].cuda()
    out_g, grad_g, info_g = _render("cuda", "cuda", scene, viewmat, K, 128, 96, **cuda_opts)
    out_c, grad_c, info_c = _render(reference, "cpu", scene, viewmat, K, 128, 96, **options)
    assert info_g["backend"] == "cuda"
    for key in out_c:
        mae = float((out_g[key] - out_c[key]).abs().mean())
        assert mae < 1e-3, f"{key}: MAE {mae}"
    agree = (info_g["visible"].cpu() == info_c["visible"]).float().mean()
    assert agree > 0.99
    for key in grad_c:
        rel = float((grad_g[key] - grad_c[key]).norm() / grad_c[key].norm())
        assert rel < 2e-2, f"gradient {key}: relative error {rel}"


@pytest.mark.gpu
def test_auto_uses_gsplat_for_cuda_tensors(gsplat_here):
    scene, viewmat, K = random_scene(100, 32, 32, seed=1)
    params = [t.cuda() for t in scene.params()]
    _, _, info = rasterize(*params, viewmat.cuda(), K.cuda(), 32, 32)
    assert info["backend"] == "cuda"
    assert info["means2d"].shape == (100, 2) and info["radii"].shape == (100, 2)


class _FakeGsplat:
    """gsplat.rasterization's documented contract (one camera, packed=False, radii [C, N] as in
    gsplat < 1.5, means2d [C, N, 2] whose .absgrad its backward sets), on the torch reference."""

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
        *,
        near_plane,
        far_plane,
        radius_clip,
        eps2d,
        packed,
        tile_size,
        backgrounds,
        render_mode,
        absgrad,
        rasterize_mode,
    ):
        cls.calls.append(
            dict(
                packed=packed,
                tile_size=tile_size,
                render_mode=render_mode,
                absgrad=absgrad,
                rasterize_mode=rasterize_mode,
                viewmats=tuple(viewmats.shape),
                Ks=tuple(Ks.shape),
                backgrounds=None if backgrounds is None else tuple(backgrounds.shape),
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
        base = proj.means2d[None] * 1.0  # a non-leaf [1, N, 2], like gsplat's
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
            "radii": proj.radii.max(dim=1).values[None],
            "depths": proj.depths[None],
            "conics": proj.conics[None],
            "opacities": proj.opacities[None],
            "isect_ids": torch.zeros(torch_reference.count_intersections(proj)),
        }
        return image[None], alpha[None], meta


@pytest.mark.parametrize(
    "options",
    [{}, {"render_depth": True, "antialiased": True}, {"background": torch.tensor([0.2, 0.3, 0.4])}],
)
def test_gsplat_wrapper_plumbing_with_a_stand_in(monkeypatch, options):
    """Everything our wrapper does around gsplat, checked against the torch backend: outputs,
    info, and info["means2d"].grad / .absgrad when the loss also uses means2d directly."""
    monkeypatch.setattr(cuda_backend, "import_gsplat", lambda: _FakeGsplat)
    scene, viewmat, K = random_scene(300, 48, 40, seed=2)
    results = {}
    for name in ("wrapper", "torch"):
        params = [t.clone().requires_grad_(True) for t in scene.params()]
        background = options.get("background")
        if name == "wrapper":
            image, alpha, depth, info = cuda_backend.rasterize(
                *params,
                viewmat,
                K,
                48,
                40,
                background,
                near_plane=0.01,
                far_plane=1e10,
                eps2d=0.3,
                radius_clip=0.0,
                antialiased=options.get("antialiased", False),
                render_depth=options.get("render_depth", False),
                depth_mode="expected",
            )
        else:
            image, alpha, info = rasterize(
                *params,
                viewmat,
                K,
                48,
                40,
                background=background,
                backend="torch",
                antialiased=options.get("antialiased", False),
                render_depth=options.get("render_depth", False),
            )
            depth = info.get("depth")
        loss = (image * torch.linspace(0, 1, 48)[None, :, None]).sum() + alpha.sum()
        loss = loss + (info["means2d"] ** 2).sum() * 1e-4  # a second, direct use of means2d
        if depth is not None:
            loss = loss + depth.sum() * 0.01
        loss.backward()
        results[name] = (image.detach(), alpha.detach(), info, [p.grad for p in params])
    (img_w, a_w, info_w, g_w), (img_t, a_t, info_t, g_t) = results["wrapper"], results["torch"]
    assert _FakeGsplat.calls[-1]["packed"] is False and _FakeGsplat.calls[-1]["tile_size"] == 16
    assert _FakeGsplat.calls[-1]["viewmats"] == (1, 4, 4) and _FakeGsplat.calls[-1]["absgrad"]
    assert torch.allclose(img_w, img_t, atol=1e-6) and torch.allclose(a_w, a_t, atol=1e-6)
    assert info_w["radii"].shape == (300, 2) and torch.equal(info_w["visible"], info_t["visible"])
    assert info_w["n_intersections"] == info_t["n_intersections"]
    for a, b in zip(g_w, g_t, strict=True):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-6)
    assert torch.allclose(info_w["means2d"].grad, info_t["means2d"].grad, rtol=1e-4, atol=1e-6)
    assert torch.allclose(info_w["means2d"].absgrad, info_t["means2d"].absgrad, rtol=1e-4, atol=1e-6)
