"""The gsplat (CUDA) backend against the CPU kernels on the same scenes. Needs a GPU and the
`cuda` extra; skipped cleanly otherwise (conftest marks `gpu` tests)."""

from __future__ import annotations

import pytest
import torch

from stg_node.splat import rasterize
from stg_node.splat.api import cpu_backend_status, cuda_backend_status
from stg_node.splat.scenes import random_scene

pytestmark = pytest.mark.gpu


@pytest.fixture(scope="module", autouse=True)
def _need_gsplat():
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


@pytest.mark.parametrize(
    "options",
    [{}, {"antialiased": True}, {"render_depth": True}, {"background": torch.tensor([0.2, 0.3, 0.4])}],
)
def test_cuda_matches_cpu(options):
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


def test_auto_uses_gsplat_for_cuda_tensors():
    scene, viewmat, K = random_scene(100, 32, 32, seed=1)
    params = [t.cuda() for t in scene.params()]
    _, _, info = rasterize(*params, viewmat.cuda(), K.cuda(), 32, 32)
    assert info["backend"] == "cuda"
    assert info["means2d"].shape == (100, 2) and info["radii"].shape == (100, 2)
