"""The C++/OpenMP backend against the torch reference (an independent implementation of the
same rules), plus its build cache, thread count and chunking."""

from __future__ import annotations

import logging
import shutil

import pytest
import torch

from stg_node.splat import build, cpu_backend, rasterize
from stg_node.splat.api import cpu_backend_status
from stg_node.splat.scenes import front_camera, person_sized_scene, random_scene

pytestmark = pytest.mark.skipif(cpu_backend_status() is not None, reason="C++ splat kernels unavailable")

PARAM_NAMES = ("means", "quats", "scales", "opacities", "colors")


def _render(backend, scene, viewmat, K, width, height, seed=0, dtype=torch.float32, **options):
    """Render, backpropagate a random linear loss; return outputs and gradients."""
    params = [t.to(dtype).clone().requires_grad_(True) for t in scene.params()]
    background = options.pop("background", None)
    if background is not None:
        background = background.to(dtype).clone().requires_grad_(True)
    image, alpha, info = rasterize(
        *params,
        viewmat.to(dtype),
        K.to(dtype),
        width,
        height,
        background=background,
        backend=backend,
        **options,
    )
    gen = torch.Generator().manual_seed(seed + 1)
    loss = (image * torch.rand(image.shape, generator=gen, dtype=torch.float64).to(dtype)).sum()
    loss = loss + (alpha * torch.rand(alpha.shape, generator=gen, dtype=torch.float64).to(dtype)).sum()
    if "depth" in info:
        loss = loss + 0.05 * (info["depth"] * torch.rand(alpha.shape, generator=gen).to(dtype)).sum()
    loss.backward()
    grads = {name: p.grad.double() for name, p in zip(PARAM_NAMES, params, strict=True)}
    if background is not None:
        grads["background"] = background.grad.double()
    grads["means2d"] = info["means2d"].grad.double()
    grads["absgrad"] = info["means2d"].absgrad.double()
    outputs = {"image": image.detach().double(), "alpha": alpha.detach().double()}
    if "depth" in info:
        outputs["depth"] = info["depth"].detach().double()
    return outputs, grads, info


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm() / b.norm().clamp_min(1e-12))


CASES = [
    dict(n=300, width=61, height=47, seed=0, channels=3),
    dict(n=800, width=96, height=80, seed=1, channels=3, background=torch.tensor([0.2, 0.4, 0.9])),
    dict(n=400, width=70, height=33, seed=2, channels=5, antialiased=True),
    dict(n=500, width=64, height=64, seed=3, channels=1, render_depth=True),
    dict(
        n=500,
        width=50,
        height=70,
        seed=4,
        channels=3,
        render_depth=True,
        depth_mode="accumulated",
        antialiased=True,
        background=torch.tensor([1.0, 1.0, 1.0]),
    ),
    # Dense and opaque: many pixels stop early on the transmittance threshold, alphas clamp.
    dict(n=2500, width=64, height=48, seed=8, channels=3, max_opacity=1.0),
    # Channel counts of the other tile paths: 6 compiled in; 7 and 9 at run time, with the
    # colours outside the per-Gaussian records.
    dict(n=600, width=40, height=52, seed=9, channels=6, max_opacity=1.0),
    dict(n=600, width=52, height=40, seed=10, channels=6, render_depth=True),
    dict(n=400, width=48, height=48, seed=11, channels=9),
]


@pytest.mark.parametrize("case", CASES, ids=[f"case{i}" for i in range(len(CASES))])
def test_cpu_matches_torch_reference(case):
    case = dict(case)
    n, width, height, seed, channels = (case.pop(k) for k in ("n", "width", "height", "seed", "channels"))
    max_opacity = case.pop("max_opacity", 0.95)
    scene, viewmat, K = random_scene(n, width, height, seed=seed, channels=channels, max_opacity=max_opacity)
    out_t, grad_t, info_t = _render("torch", scene, viewmat, K, width, height, seed, **dict(case))
    out_c, grad_c, info_c = _render("cpu", scene, viewmat, K, width, height, seed, **dict(case))
    assert info_c["backend"] == "cpu" and info_t["backend"] == "torch"
    # The scene must actually exercise the renderer.
    assert out_t["alpha"].mean() > 0.25
    assert int(info_t["visible"].sum()) > n // 3
    for key in out_t:
        mae = float((out_t[key] - out_c[key]).abs().mean())
        assert mae < 1e-4, f"{key}: MAE {mae}"
    assert torch.equal(info_t["visible"], info_c["visible"])
    assert torch.equal(info_t["radii"], info_c["radii"])
    assert info_t["n_intersections"] == info_c["n_intersections"]
    assert torch.allclose(info_t["means2d"].detach(), info_c["means2d"].detach(), atol=1e-3)
    for name in grad_t:
        rel = _rel(grad_c[name], grad_t[name])
        assert rel < 1e-3, f"gradient of {name}: relative error {rel}"


def test_cpu_float32_matches_float64_reference():
    """Against the reference in float64 (a more exact oracle than float32)."""
    scene, viewmat, K = random_scene(400, 80, 60, seed=11)
    out_t, grad_t, _ = _render("torch", scene, viewmat, K, 80, 60, 11, dtype=torch.float64)
    out_c, grad_c, _ = _render("cpu", scene, viewmat, K, 80, 60, 11)
    assert float((out_t["image"] - out_c["image"]).abs().mean()) < 1e-4
    for name in grad_t:
        assert _rel(grad_c[name], grad_t[name]) < 1e-3, name


def test_thread_count_does_not_change_results():
    scene = person_sized_scene(3000, seed=5)
    viewmat, K = front_camera(128, 128)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        out1, grad1, _ = _render("cpu", scene, viewmat, K, 128, 128)
        torch.set_num_threads(2)
        out2, grad2, _ = _render("cpu", scene, viewmat, K, 128, 128)
    finally:
        torch.set_num_threads(before)
    assert torch.equal(out1["image"], out2["image"])  # tiles are independent: bitwise equal
    for name in grad1:  # per-thread buffers are summed in another order
        assert _rel(grad2[name], grad1[name]) < 1e-5, name


def test_chunked_rasterization_equals_single_pass():
    """A tiny intersection budget forces many chunks; the result must not change."""
    scene, viewmat, K = random_scene(400, 64, 48, seed=6)
    out1, grad1, info1 = _render("cpu", scene, viewmat, K, 64, 48)
    stats_single = info1["stats"]["forward"]
    out2, grad2, info2 = _render("cpu", scene, viewmat, K, 64, 48, max_intersections=100)
    stats_chunked = info2["stats"]["forward"]
    assert info2["stats"]["backward"]["n_chunks"] == stats_chunked["n_chunks"]  # filled by backward
    assert stats_single["n_chunks"] == 1
    assert stats_chunked["n_chunks"] > 5
    assert stats_chunked["n_intersections"] == stats_single["n_intersections"]
    assert torch.equal(out1["image"], out2["image"])
    for name in grad1:  # same contributions, summed in another order across threads
        assert _rel(grad2[name], grad1[name]) < 1e-5, name


def test_absgrad_is_sum_of_per_pixel_absolute_gradients():
    """AbsGS statistic against a per-pixel Jacobian computed by autograd on the reference."""
    from stg_node.splat import torch_reference

    means = torch.tensor([[0.01, -0.02, 2.0], [0.05, 0.03, 2.6]], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0.2, 0.0, 0.1], [0.9, 0.0, 0.3, 0.0]], dtype=torch.float64)
    scales = torch.tensor([[0.03, 0.02, 0.02], [0.04, 0.05, 0.01]], dtype=torch.float64)
    opacities = torch.tensor([0.8, 0.7], dtype=torch.float64)
    colors = torch.tensor([[1.0], [0.5]], dtype=torch.float64)
    K = torch.tensor([[100.0, 0.0, 10.3], [0.0, 100.0, 9.6], [0.0, 0.0, 1.0]], dtype=torch.float64)
    weights = torch.rand(20, 20, 1, generator=torch.Generator().manual_seed(0), dtype=torch.float64) - 0.3

    proj = torch_reference.project(
        means, quats, scales, opacities, torch.eye(4, dtype=torch.float64), K, 20, 20
    )

    def weighted_image(m2):
        proj.means2d = m2
        image, _ = torch_reference.rasterize(proj, colors, 20, 20)
        return image * weights

    jac = torch.autograd.functional.jacobian(weighted_image, proj.means2d.detach().clone())  # [20,20,1,2,2]
    expected_abs = jac.abs().sum(dim=(0, 1, 2))
    expected_grad = jac.sum(dim=(0, 1, 2))
    assert expected_abs.min() > 1e-2

    for backend in ("torch", "cpu"):
        dtype = torch.float64 if backend == "torch" else torch.float32
        params = [t.to(dtype).clone().requires_grad_(True) for t in (means, quats, scales, opacities, colors)]
        image, _, info = rasterize(*params, torch.eye(4, dtype=dtype), K.to(dtype), 20, 20, backend=backend)
        (image * weights.to(dtype)).sum().backward()
        tol = 1e-9 if dtype == torch.float64 else 1e-4
        assert torch.allclose(info["means2d"].absgrad.double(), expected_abs, rtol=tol, atol=tol), backend
        assert torch.allclose(info["means2d"].grad.double(), expected_grad, rtol=tol, atol=tol), backend


def test_build_key_depends_on_sources_flags_and_compiler(tmp_path):
    src = tmp_path / "csrc"
    shutil.copytree(build.CSRC_DIR, src)
    base = build.build_key(src, ["-O3"], "g++ 12")
    assert build.build_key(src, ["-O3"], "g++ 12") == base
    assert build.build_key(src, ["-O3", "-mavx2"], "g++ 12") != base
    assert build.build_key(src, ["-O3"], "g++ 13") != base
    (src / "splat_kernels.cpp").write_text((src / "splat_kernels.cpp").read_text() + "\n// changed\n")
    assert build.build_key(src, ["-O3"], "g++ 12") != base


def test_arch_flags_follow_the_cpu_and_the_override(monkeypatch):
    monkeypatch.setenv(build.ENV_ARCH_FLAGS, "-march=native -mtune=native")
    assert build.arch_flags() == ["-march=native", "-mtune=native"]
    monkeypatch.setenv(build.ENV_ARCH_FLAGS, "")
    assert build.arch_flags() == []
    monkeypatch.delenv(build.ENV_ARCH_FLAGS)
    monkeypatch.setattr(build, "_cpu_flags", lambda: {"sse4_2", "avx"})
    assert build.arch_flags() == []
    monkeypatch.setattr(build, "_cpu_flags", lambda: set(build.X86_V3_FEATURES) | {"sse4_2"})
    monkeypatch.setattr(build.platform, "machine", lambda: "x86_64")
    assert build.arch_flags() == list(build.X86_V3_FLAGS)


def test_missing_compiler_is_reported_and_auto_falls_back(monkeypatch, tmp_path, caplog):
    monkeypatch.setenv("CXX", "no-such-compiler-stg")
    monkeypatch.setenv(build.ENV_CACHE, str(tmp_path))
    with pytest.raises(build.ExtensionUnavailable, match="no C\\+\\+ compiler") as err:
        build.build_extension()
    assert err.value.reason == "no-compiler"

    from stg_node.splat import api

    def unavailable():
        raise build.ExtensionUnavailable("no C++ compiler found (test)", reason="no-compiler")

    monkeypatch.setattr(cpu_backend, "load_kernels", unavailable)
    monkeypatch.setattr(api, "_warned", set())
    monkeypatch.setattr(api, "_logged_choices", set())
    scene, viewmat, K = random_scene(20, 16, 16)
    with caplog.at_level(logging.INFO, logger="stg_node.splat.api"):
        with pytest.warns(RuntimeWarning, match="no C\\+\\+ compiler found"):
            _, _, info = rasterize(*scene.params(), viewmat, K, 16, 16)
        _, _, info2 = rasterize(*scene.params(), viewmat, K, 16, 16)  # no second warning
    assert info["backend"] == info2["backend"] == "torch"
    choices = [r for r in caplog.records if "splat backend for cpu tensors" in r.getMessage()]
    assert len(choices) == 1
    with pytest.raises(build.ExtensionUnavailable):
        rasterize(*scene.params(), viewmat, K, 16, 16, backend="cpu")


def test_build_failure_names_the_compiler_log(monkeypatch, tmp_path):
    src = tmp_path / "csrc"
    shutil.copytree(build.CSRC_DIR, src)
    for name in build.SOURCES:  # break both at the top so the compiler stops at once
        path = src / name
        path.write_text("#error deliberately broken for the test\n" + path.read_text())
    monkeypatch.setenv(build.ENV_ARCH_FLAGS, "-Wfatal-errors")
    with pytest.raises(build.ExtensionUnavailable, match="compiler output is in") as err:
        build.build_extension(source_dir=src, cache_dir=tmp_path / "cache")
    assert err.value.reason == "build-failed"
    assert err.value.log_path.is_file()
    assert "deliberately broken" in err.value.log_path.read_text()


def test_cached_build_is_reused(monkeypatch):
    kernels = build.load_kernels()
    assert kernels.library.is_file()
    assert kernels.ops.tile_size() == 16
    # A second build_extension in the same process loads the cached library without ninja.
    from torch.utils import cpp_extension

    monkeypatch.setattr(cpp_extension, "load", lambda *a, **k: pytest.fail("rebuilt a cached extension"))
    again = build.build_extension(cache_dir=kernels.library.parent.parent)
    assert again.namespace == kernels.namespace
