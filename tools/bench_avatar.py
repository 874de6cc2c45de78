"""Speed of the avatar's training step (phase by phase) and of its rendering, with same-run baselines.

    python tools/bench_avatar.py [--data DIR] [--steps 60] [--threads 1] [--gaussians 20000 50000]

1. Training step at the benchmark's 512x512 (the person's crop is rendered): per-phase wall time
   (data, pose = LBS + spacetime + colour, flow target, render, loss, backward, update, densify),
   and the whole step against the rasterizer's own forward+backward on the same Gaussians
   (the baseline: what a step costs beyond splatting).
2. SSIM loss (forward+backward, a 420x200 crop): the C++ kernel (stg_node.splat.image_ops.ssim) against
   the torch implementation (depthwise separable convolutions, autograd; the fallback) and kornia's.
3. Rendering a posed avatar at 512x512 (pose + colour + splat) with N Gaussians, with 0 %, 10 %
   and 100 % of them carrying motion terms; the zero-motion skip against evaluating every row,
   against the same avatar's rigid part alone (LBS only: what a static row should cost) and
   against the bare rasterizer (baseline).

The data is generated if --data is not given (stg-synth, 125 frames, 100 for training).
Figures go to docs/BENCHMARKS.md with this command line and the machine.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stg_node.threads import configure_threads  # noqa: E402


def _machine() -> str:
    return f"{platform.machine()}, {torch.get_num_threads()} torch thread(s), {platform.processor() or 'cpu'}"


def ensure_data(path: str | None) -> Path:
    if path:
        return Path(path)
    out = Path(tempfile.gettempdir()) / "stg_bench_avatar_synth"
    if not (out / "synth.json").is_file():
        from stg_node.data.synth.generate import SynthConfig, generate

        generate(SynthConfig(out=out, num_frames=125, overwrite=True), progress=False)
    return out


def bench_step(data: Path, steps: int, gaussians: int) -> dict:
    from stg_node.avatar import Trainer, preset
    from stg_node.avatar.data_spec import DataSpec
    from stg_node.avatar.model import render
    from stg_node.avatar.trainer import StepProfile

    config = preset("balanced").replace(
        **{
            "model.num_gaussians": gaussians,
            "model.max_gaussians": gaussians,
            "densify.start_iter": 10,
            "densify.interval": 20,
        }
    )
    trainer = Trainer(config, seed=0)
    t0 = time.perf_counter()
    trainer.add_frames(DataSpec(str(data), "synthetic").open("train"))
    load_s = time.perf_counter() - t0
    for _ in range(5):
        trainer.step()
    trainer.profile = StepProfile()
    t0 = time.perf_counter()
    for _ in range(steps):
        trainer.step()
    step_ms = 1e3 * (time.perf_counter() - t0) / steps
    phases = trainer.profile.per_step_ms()
    # Baseline: the rasterizer alone, forward + backward, on the same posed Gaussians and crops.
    stored = trainer.store.frames[0]
    from stg_node.avatar.model import BodyState, Camera3

    cam = Camera3.from_camera(stored.frame.camera, stored.crop)
    with torch.no_grad():
        posed = trainer.model.pose(BodyState.from_smpl(stored.frame.smpl), 0.0, cam.center)
    leaves = [
        t.detach().clone().requires_grad_(True)
        for t in (posed.means, posed.quats, posed.scales, posed.opacities, posed.colors)
    ]
    times = []
    for _ in range(max(steps // 2, 5)):
        posed.means, posed.quats, posed.scales, posed.opacities, posed.colors = leaves
        t = time.perf_counter()
        image, alpha, _ = render(posed, cam, background=0.0, backend=trainer.backend)
        (image.sum() + alpha.sum()).backward()
        times.append(time.perf_counter() - t)
    raster_ms = 1e3 * statistics.median(times)
    return {
        "gaussians": trainer.model.table.num,
        "load_s": load_s,
        "step_ms": step_ms,
        "phases_ms": phases,
        "raster_fwd_bwd_ms": raster_ms,
        "step_over_raster": step_ms / raster_ms,
    }


def bench_ssim(repeats: int) -> dict:
    """SSIM loss forward+backward on a 420x200 crop: the C++ kernel the loss uses on CPU float32
    (image_ops.ssim, analytic backward) against the torch implementation it replaced (and keeps as
    the fallback) and kornia's ssim_loss, in the same run."""
    import kornia

    from stg_node.avatar.losses import ssim_torch
    from stg_node.splat.image_ops import ssim as ssim_kernel

    gen = torch.Generator().manual_seed(0)
    a = torch.rand(420, 200, 3, generator=gen, requires_grad=True)
    b = torch.rand(420, 200, 3, generator=gen)

    def ssim_kornia(x, y):  # kornia's loss is (1 - SSIM) / 2 of (1, C, H, W) images
        return 1 - 2 * kornia.losses.ssim_loss(
            x.permute(2, 0, 1)[None], y.permute(2, 0, 1)[None], 11, padding="valid"
        )

    contenders = {"kernel": ssim_kernel, "torch": ssim_torch, "kornia": ssim_kornia}
    out = {}
    for name, fn in contenders.items():
        for _ in range(3):
            (1 - fn(a, b)).backward()
        runs = []
        for _ in range(repeats):
            t = time.perf_counter()
            (1 - fn(a, b)).backward()
            runs.append(time.perf_counter() - t)
        out[name] = 1e3 * statistics.median(runs)
    with torch.no_grad():
        values = {name: float(fn(a, b)) for name, fn in contenders.items()}
    out["agree"] = max(abs(values["kernel"] - values[k]) for k in ("torch", "kornia"))
    out["torch_over_kernel"] = out["torch"] / out["kernel"]
    out["kornia_over_kernel"] = out["kornia"] / out["kernel"]
    return out


def bench_render(data: Path, gaussians: int, repeats: int) -> list[dict]:
    from stg_node.avatar import AvatarRenderer, preset
    from stg_node.avatar.data_spec import DataSpec
    from stg_node.avatar.gaussians import MOTION_COLUMNS
    from stg_node.avatar.model import BodyState, Camera3, render
    from stg_node.avatar.nonrigid import rigid_part
    from stg_node.avatar.trainer import Trainer

    train = DataSpec(str(data), "synthetic").open("train")
    sample = train[0]
    config = preset("balanced").replace(
        **{"model.num_gaussians": gaussians, "model.max_gaussians": gaussians}
    )
    trainer = Trainer(config, seed=0)
    trainer.add_frame(__import__("stg_node.avatar", fromlist=["TrainFrame"]).TrainFrame.from_sample(sample))
    model = trainer.model
    renderer = AvatarRenderer(model)
    table = model.table
    gen = torch.Generator().manual_seed(0)
    rows = []
    cam = Camera3.from_camera(sample.camera)
    with torch.no_grad():
        posed = model.pose(BodyState.from_smpl(sample.smpl), 0.0, cam.center)

    def pose_and_render(skip: bool, avatar=model):
        body = BodyState.from_smpl(sample.smpl)
        return render(avatar.pose(body, 0.1, cam.center, skip_inactive=skip), cam, background=0.0)

    rigid, _ = rigid_part(model)
    # The cases alternate run by run, so load on a shared machine falls on each alike.
    cases = {
        "ms_skip": lambda: pose_and_render(True),
        "ms_all": lambda: pose_and_render(False),
        "ms_lbs": lambda: pose_and_render(True, rigid),
        "ms_raster_only": lambda: render(posed, cam, background=0.0),
    }
    if model.motion_bases is not None:  # shared bases: some motion, so moving rows do move
        with torch.no_grad():
            model.motion_bases.values.copy_(
                torch.randn(model.motion_bases.values.shape, generator=gen) * 1e-3
            )
    for fraction in (0.0, 0.1, 1.0):
        with torch.no_grad():
            active = torch.rand(table.num, generator=gen) < fraction
            for name in MOTION_COLUMNS:
                if name in table:
                    table[name].zero_()
                    table[name][active] = 1e-3
        result = {"gaussians": table.num, "active_fraction": fraction}
        runs = {name: [] for name in cases}
        for _ in range(repeats + 2):
            for name, case in cases.items():
                t = time.perf_counter()
                with torch.no_grad():
                    case()
                runs[name].append(time.perf_counter() - t)
        for name, times in runs.items():
            result[name] = 1e3 * statistics.median(times[2:])
        result["fps_skip"] = 1e3 / result["ms_skip"]
        rows.append(result)
    del renderer
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=None, help="an stg-synth folder (default: generated once in /tmp)")
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--threads", default="1")
    parser.add_argument("--gaussians", type=int, nargs="+", default=[20000, 50000])
    parser.add_argument("--skip", nargs="*", default=[], choices=("step", "ssim", "render"))
    args = parser.parse_args(argv)
    configure_threads(args.threads)
    data = ensure_data(args.data)
    print(f"# machine: {_machine()}")
    if "ssim" not in args.skip:
        s = bench_ssim(args.repeats)
        print(
            f"ssim fwd+bwd 420x200: C++ kernel {s['kernel']:.2f} ms, torch {s['torch']:.1f} ms, "
            f"kornia {s['kornia']:.1f} ms (torch / kernel = {s['torch_over_kernel']:.1f}x, "
            f"kornia / kernel = {s['kornia_over_kernel']:.1f}x; values agree to {s['agree']:.1e})"
        )
    for n in args.gaussians:
        if "step" not in args.skip:
            r = bench_step(data, args.steps, n)
            phases = ", ".join(f"{k} {v:.1f}" for k, v in r["phases_ms"].items())
            print(
                f"step {r['gaussians']} Gaussians: {r['step_ms']:.1f} ms ({1e3 / r['step_ms']:.1f} it/s); "
                f"rasterizer fwd+bwd alone {r['raster_fwd_bwd_ms']:.1f} ms "
                f"(step / raster = {r['step_over_raster']:.2f}x); "
                f"phases ms: {phases}; loading 100 frames + flow {r['load_s']:.1f} s"
            )
        if "render" not in args.skip:
            for r in bench_render(data, n, args.repeats):
                print(
                    f"render 512x512 {r['gaussians']} Gaussians, {100 * r['active_fraction']:.0f}% moving: "
                    f"{r['ms_skip']:.1f} ms ({r['fps_skip']:.1f} FPS) with the zero-motion skip, "
                    f"{r['ms_all']:.1f} ms evaluating every row (x{r['ms_all'] / r['ms_skip']:.2f}); "
                    f"its rigid part alone (LBS) {r['ms_lbs']:.1f} ms (skip / LBS = "
                    f"{r['ms_skip'] / r['ms_lbs']:.2f}x); rasterizer alone {r['ms_raster_only']:.1f} ms"
                )
    return 0


if __name__ == "__main__":
    sys.exit(main())
