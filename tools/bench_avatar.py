"""Speed of the avatar's training step and posed render, against an older revision in the same run.

    python tools/bench_avatar.py [--data DIR] [--baseline REV | --no-baseline] [--rounds 3]
                                 [--gaussians 20000 50000] [--only step render extremes ssim skip quality]
                                 [--device cuda]

Every timed case runs in a child process (``--worker``), once on this tree and once on the
baseline revision (tools/baseline.py exports it; default: the code before issue 24), alternating
which goes first, ``--rounds`` times; the figure is the median over rounds of each child's
median. Children report wall time and their own CPU time (``time.thread_time``): on a machine
shared with other processes the CPU time is what the code costs, the wall time what a user saw.
The 1-minute load average is printed with every row.

1. step: a training step of the balanced preset at a fixed Gaussian count (the person's crop of a
   512x512 frame is rendered): per-phase CPU time (data, pose = LBS + spacetime + colour, flow
   target, render, loss, backward, update, densify) and the whole step against the rasterizer's
   own forward+backward on the same Gaussians and crop (what a step costs beyond splatting).
   Target (issue 24): step <= 2x the rasterizer. Also timed: the rasterizer with the two flow
   channels a step splats along with RGB (what the step's own splatting costs).
2. render: a posed avatar at 512x512 (pose + colour + splat, AvatarRenderer) over 60 consecutive
   frames of the benchmark (one camera following the body): ``exact`` (every colour every frame)
   and ``stream`` (colours recomputed in turns, every 2nd frame: the renderer node's default,
   ``color_refresh``), against the baseline's renderer. Targets: >= 60 FPS at 20k Gaussians,
   >= 30 FPS at 50k, one thread.
3. extremes: the tiny and huge cases of docs/STABILITY.md: a posed render at 16x16, 64x64 and
   2048x2048 (20k Gaussians) and of 1,000,000 Gaussians at 512x512, and a training step at
   64x64. Target: nothing slower than the baseline.
4. ssim: the loss's SSIM, forward+backward on a 420x200 crop: the C++ kernel against the torch
   implementation and kornia's (this tree only, one process).
5. skip: posed renders with 0 %, 10 %, 100 % of the Gaussians moving, with and without the
   zero-motion skip, against the same avatar's rigid part alone (LBS only: what a static row
   should cost) and the bare rasterizer (this tree only, one process).
6. streams: what a colour stream costs in the image: a fast-preset model trained 300 steps,
   30 consecutive frames rendered with colours recomputed every 2nd, 3rd, 4th frame against
   the exact renders (PSNR of the 8-bit images, largest difference in grey levels; this tree).
7. quality (only with ``--only quality``): the same result. A fast-preset model trained at the
   mid scale of tools/tradeoff.py (256 px, iterations / 3, Gaussian budgets / 2; seed 0) in each
   tree, scored on the benchmark's held-out views and its novel poses (PSNR, SSIM), with its
   training CPU time.
   Target (issue 24): no more than 0.1 dB below the baseline (a gain is reported, not missed).
   ``--quality-scale quick`` for a smoke run.

With ``--device cuda`` the step and render cases run on the GPU (cuda splatting backend, gsplat),
this tree only: the figures are wall times with the device synchronised around each timed call,
and the same-run baselines are the rasterizer alone on the same device and the cpu rows.

The data is generated if --data is not given (stg-synth, 125 frames, 100 for training).
A row is printed once all its children are done (2 x ``--rounds`` of them for a render row); while
they run, each child's phases (start-up, model, first render, timed loop, ...) go to stderr with the
seconds since it started, so a run cut by a time limit still shows where its time went. A stopped
bench (SIGTERM, Ctrl-C) stops the child it is measuring.
Figures go to docs/BENCHMARKS.md with this command line, the machine and the load.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

from baseline import BASELINE_REV, child_env, export_revision  # noqa: E402

STEP_TARGET = 2.0  # step / rasterizer fwd+bwd
RENDER_TARGETS = {20_000: 60.0, 50_000: 30.0}  # FPS, one thread, 512x512
EXTREME_RENDERS = (
    ("20k at 16x16", 20_000, 16),
    ("20k at 64x64", 20_000, 64),
    ("20k at 2048x2048", 20_000, 2048),
)
MILLION = ("1M at 512x512", 1_000_000, 512)


def _machine() -> str:
    cpu = platform.processor() or "cpu"
    return f"{platform.machine()}, {os.cpu_count()} cpus, {cpu}, Python {platform.python_version()}"


def _device_name(device: str) -> str:
    if device == "cpu":
        return "cpu"
    import torch

    return torch.cuda.get_device_name()


def ensure_data(path: str | None) -> Path:
    if path:
        return Path(path)
    out = Path(tempfile.gettempdir()) / "stg_bench_avatar_synth"
    if not (out / "synth.json").is_file():
        print(f"# generating the benchmark's data in {out} (once per machine)", file=sys.stderr, flush=True)
        sys.path.insert(0, str(ROOT))
        from stg_node.data.synth.generate import SynthConfig, generate

        generate(SynthConfig(out=out, num_frames=125, overwrite=True), progress=False)
    return out


# ---- the children ----------------------------------------------------------------------------------


def _sync_for(device: str):
    """What makes a wall time honest on `device`: CUDA kernels run asynchronously."""
    if device == "cuda":
        import torch

        return torch.cuda.synchronize
    return lambda: None


PHASE_MARK = "bench-phase\t"  # a child's progress line on stderr: mark, seconds, what it has done
_child_started = time.perf_counter()


def _phase(done: str) -> None:
    """Tell the parent what this child has finished so far (the parent shows it as it comes)."""
    print(f"{PHASE_MARK}{time.perf_counter() - _child_started:.1f}\t{done}", file=sys.stderr, flush=True)


def _device_ready(device: str) -> None:
    """Start-up as a phase of its own: the imports, and on a GPU the CUDA context."""
    _phase("imports")
    if device != "cpu":
        import torch

        torch.zeros(1, device=device)
        _phase(f"{device} context ready")


def _timed(fn, repeats: int, warmup: int = 2, sync=lambda: None) -> dict:
    for _ in range(warmup):
        fn()
    wall, cpu = [], []
    for _ in range(repeats):
        sync()
        w, c = time.perf_counter(), time.thread_time()
        fn()
        sync()
        cpu.append(time.thread_time() - c)
        wall.append(time.perf_counter() - w)
    return {"wall_ms": 1e3 * statistics.median(wall), "cpu_ms": 1e3 * statistics.median(cpu)}


def _cpu_profile_class():
    """StepProfile counting this thread's CPU time (written here: older trees have no clock option)."""
    from stg_node.avatar.trainer import StepProfile

    class CpuProfile(StepProfile):
        def start(self) -> None:
            self._last = time.thread_time()

        def mark(self, phase: str) -> None:
            now = time.thread_time()
            self.seconds[phase] += now - self._last
            self._last = now

    return CpuProfile


def _balanced(n: int, **more):
    from stg_node.avatar import preset

    return preset("balanced").replace(**{"model.num_gaussians": n, "model.max_gaussians": n, **more})


def worker_step(spec: dict) -> dict:
    import torch

    from stg_node.avatar import Trainer
    from stg_node.avatar.data_spec import DataSpec
    from stg_node.avatar.model import BodyState, Camera3, render
    from stg_node.avatar.trainer import StepProfile

    n, steps = spec["gaussians"], spec["steps"]
    device = spec.get("device", "cpu")
    sync = _sync_for(device)
    config = _balanced(n, **{"densify.start_iter": 10, "densify.interval": 20})
    _device_ready(device)
    trainer = Trainer(config, seed=0, **_device_args(device))
    size = spec.get("size")
    frames = DataSpec(spec["data"], "synthetic", **({"size": size} if size else {})).open("train")
    trainer.add_frames(frames)
    _phase(f"model of {trainer.model.table.num} Gaussians, {len(frames)} frames added")
    for _ in range(5):
        trainer.step()
    _phase("5 warm-up steps")
    # on CUDA the phases are host wall time (kernels run asynchronously: read them as launch cost)
    trainer.profile = _cpu_profile_class()() if device == "cpu" else StepProfile()
    wall, cpu = [], []
    for _ in range(steps):
        sync()
        w, c = time.perf_counter(), time.thread_time()
        trainer.step()
        sync()
        cpu.append(time.thread_time() - c)
        wall.append(time.perf_counter() - w)
    phases = trainer.profile.per_step_ms()
    _phase(f"{steps} timed steps")
    # the rasterizer alone, forward + backward, on the same posed Gaussians and crop
    stored = trainer.store.frames[0]
    cam = Camera3.from_camera(stored.frame.camera, stored.crop, device)
    with torch.no_grad():
        body = BodyState.from_smpl(stored.frame.smpl, trainer.device)
        posed = trainer.model.pose(body, 0.0, cam.center)
    leaves = [
        t.detach().clone().requires_grad_(True)
        for t in (posed.means, posed.quats, posed.scales, posed.opacities, posed.colors)
    ]

    def raster():
        posed.means, posed.quats, posed.scales, posed.opacities, posed.colors = leaves
        image, alpha, _ = render(posed, cam, background=0.0, backend=trainer.backend)
        (image.sum() + alpha.sum()).backward()

    alone = _timed(raster, max(steps // 2, 5), sync=sync)
    # ... and with the two flow channels a step splats along with RGB (its flow loss)
    flow = torch.zeros(leaves[0].shape[0], 2, device=leaves[0].device, requires_grad=True)

    def raster_with_flow():
        posed.means, posed.quats, posed.scales, posed.opacities, posed.colors = leaves
        image, alpha, _ = render(posed, cam, background=0.0, backend=trainer.backend, extra_channels=flow)
        (image.sum() + alpha.sum()).backward()

    with_flow = _timed(raster_with_flow, max(steps // 2, 5), sync=sync)
    _phase("rasterizer alone")
    return {
        "gaussians": trainer.model.table.num,
        "step_wall_ms": 1e3 * statistics.median(wall),
        "step_cpu_ms": 1e3 * statistics.median(cpu),
        "step_cpu_mean_ms": 1e3 * statistics.mean(cpu),  # with terms on every k-th step only, the mean
        "phases_cpu_ms": phases,
        "raster_wall_ms": alone["wall_ms"],
        "raster_cpu_ms": alone["cpu_ms"],
        "raster_flow_cpu_ms": with_flow["cpu_ms"],
    }


def worker_render(spec: dict) -> dict:
    """Posed renders of an avatar with N Gaussians over consecutive frames (one camera following the
    body): ``mode`` exact (every colour every frame) or stream (colours in turns, every 2nd frame)."""
    import inspect

    import torch

    from stg_node.avatar import AvatarRenderer, Trainer, TrainFrame
    from stg_node.avatar.data_spec import DataSpec
    from stg_node.avatar.model import BodyState, Camera3, render

    device = spec.get("device", "cpu")
    sync = _sync_for(device)
    backend = _device_args(device).get("backend", "auto")
    _device_ready(device)
    train = DataSpec(spec["data"], "synthetic").open("train")
    trainer = Trainer(_balanced(spec["gaussians"]), seed=0, **_device_args(device))
    trainer.add_frame(TrainFrame.from_sample(train[0]))
    model = trainer.model
    _phase(f"model of {model.table.num} Gaussians")
    stream = spec["mode"] == "stream"
    if stream:
        if "color_refresh_every" not in inspect.signature(AvatarRenderer).parameters:
            return {"unsupported": "no colour streams in this tree"}
        renderer = AvatarRenderer(model, color_refresh_every=2, **_device_args(device, trainer=False))
    else:
        renderer = AvatarRenderer(model, **_device_args(device, trainer=False))
    frames = [train[i] for i in range(min(len(train), spec["frames"]))]
    from stg_node.nodes.convert import resized_camera

    cameras = [resized_camera(f.camera, spec["size"]) for f in frames]
    extra = {"stream": "bench"} if stream else {}
    _phase(f"{len(frames)} frames read")
    wall, cpu, drawn = [], [], 0
    for _ in range(spec["passes"]):
        for frame, camera in zip(frames, cameras, strict=False):
            sync()
            w, c = time.perf_counter(), time.thread_time()
            out = renderer.render(camera, frame.smpl, time=frame.time, **extra)
            sync()
            cpu.append(time.thread_time() - c)
            wall.append(time.perf_counter() - w)
            drawn = out.num_rendered
            if len(wall) == 1:  # the first builds the caches (and, on a GPU, loads the kernels)
                _phase(f"first render ({1e3 * wall[0]:.0f} ms)")
    _phase(f"{len(wall)} renders")
    skip = min(5, len(wall) // 4)  # the first renders build caches (effective weights, colours)
    result = {
        "gaussians": model.table.num,
        "wall_ms": 1e3 * statistics.median(wall[skip:]),
        "cpu_ms": 1e3 * statistics.median(cpu[skip:]),
        "rendered": drawn,
    }
    # the rasterizer alone on the first frame's posed Gaussians
    cam = Camera3.from_camera(cameras[0], device=device)
    with torch.no_grad():
        body = BodyState.from_smpl(frames[0].smpl, trainer.device)
        posed = model.pose(body, model.time_axis(frames[0].time), cam.center)

    def raster():
        with torch.no_grad():
            render(posed, cam, background=0.0, backend=backend)

    alone = _timed(raster, 10, sync=sync)
    _phase("rasterizer alone")
    result["raster_wall_ms"], result["raster_cpu_ms"] = alone["wall_ms"], alone["cpu_ms"]
    return result


def _device_args(device: str, trainer: bool = True) -> dict:
    """Trainer/renderer keywords for `device`: on CUDA the cuda splatting backend (gsplat)."""
    if device == "cpu":
        return {}
    return {"device": device, "backend": "cuda"} if trainer else {"backend": "cuda"}


def worker_quality(spec: dict) -> dict:
    """The same result: a fast-preset model trained at the mid scale of tools/tradeoff.py (256 px,
    iterations / 3, Gaussian budgets / 2) on the benchmark's training frames, seed 0, scored on its
    held-out views and novel poses; ``changes``: config keys set on top (only the ones this tree knows)."""
    import dataclasses

    from tradeoff import SCALES, scaled

    from stg_node.avatar import Trainer, preset
    from stg_node.avatar.data_spec import DataSpec
    from stg_node.avatar.evaluate import evaluate_trainer

    scale = SCALES[spec["scale"]]
    config = scaled(preset("fast"), scale)
    known = {}
    for key, value in spec.get("changes", {}).items():
        group, _, name = key.rpartition(".")
        fields = {f.name for f in dataclasses.fields(getattr(config, group) if group else config)}
        if name in fields:
            known[key] = value
    config = config.replace(**known)
    trainer = Trainer(config, seed=0)
    trainer.add_frames(DataSpec(spec["data"], "synthetic", size=scale.size).open("train"))
    started = time.thread_time()
    for _ in range(config.iterations):
        trainer.step()
    train_s = time.thread_time() - started
    scores = evaluate_trainer(trainer, spec["data"], split="novel_view", lpips_net=None)
    poses = evaluate_trainer(trainer, spec["data"], split="novel_pose", lpips_net=None)
    return {
        "psnr": scores["psnr"],
        "ssim": scores["ssim"],
        "pose_psnr": poses["psnr"],
        "pose_ssim": poses["ssim"],
        "train_cpu_s": train_s,
        "iterations": config.iterations,
        "gaussians": trainer.model.table.num,
        "applied": known,
    }


WORKERS = {"step": worker_step, "render": worker_render, "quality": worker_quality}


def run_worker(spec_text: str, root: str) -> None:
    sys.path.insert(0, root)
    from stg_node.threads import configure_threads

    configure_threads("1")
    spec = json.loads(spec_text)
    print(json.dumps(WORKERS[spec["case"]](spec)), flush=True)


# ---- the parent ------------------------------------------------------------------------------------


def child_label(spec: dict, tree: str) -> str:
    """What a progress line names: the case, its size and mode, the tree."""
    parts = [spec["case"], str(spec.get("gaussians", "")), spec.get("mode", ""), tree]
    return " ".join(p for p in parts if p)


def spawn(spec: dict, root: Path, label: str | None = None, progress=sys.stderr) -> dict:
    """Run one child on ``root``'s stg_node; its phases are shown on ``progress`` as they come."""
    env = child_env(root, STG_THREADS="1")
    cmd = [sys.executable, __file__, "--worker", json.dumps(spec), "--root", str(root)]
    what = f"the {spec['case']} child on {root}"
    return run_child(cmd, env, label or child_label(spec, root.name), what, progress)


def run_child(cmd: list[str], env: dict, label: str, what: str, progress=sys.stderr) -> dict:
    """The JSON result (last stdout line) of the child ``cmd``; its phase lines on stderr (PHASE_MARK)
    are shown on ``progress`` as they come, prefixed with ``label``; anything else it writes there is
    kept for the error naming ``what`` if it fails."""
    started = time.perf_counter()
    with subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as child:
        stdout: list[str] = []  # read beside stderr, so neither pipe can fill and stall the child
        reader = threading.Thread(target=lambda: stdout.extend(child.stdout), daemon=True)
        reader.start()
        errors: list[str] = []
        try:
            for line in child.stderr:
                if line.startswith(PHASE_MARK):
                    seconds, done = line[len(PHASE_MARK) :].rstrip("\n").split("\t", 1)
                    print(f"  [{label}] {float(seconds):6.1f} s: {done}", file=progress, flush=True)
                else:
                    errors.append(line)
            child.wait()
        except BaseException:  # stopped (Ctrl-C, a time limit's SIGTERM): no child left measuring
            child.kill()
            raise
        reader.join()
    if child.returncode != 0:
        raise SystemExit(f"bench: {what} failed (exit {child.returncode}):\n{''.join(errors)[-4000:]}")
    print(f"  [{label}] done after {time.perf_counter() - started:.1f} s", file=progress, flush=True)
    return json.loads("".join(stdout).strip().splitlines()[-1])


def interleaved(spec: dict, trees: dict[str, Path], rounds: int) -> dict[str, dict]:
    """Each tree's results (median over rounds of every numeric field), the trees alternating."""
    runs: dict[str, list[dict]] = {name: [] for name in trees}
    loads = []
    names = list(trees)
    for r in range(rounds):
        for name in names if r % 2 == 0 else names[::-1]:
            loads.append(os.getloadavg()[0])
            runs[name].append(spawn(spec, trees[name], child_label(spec, name)))
    out = {}
    for name, results in runs.items():
        merged: dict = {}
        for key, value in results[0].items():
            if isinstance(value, (int, float)):
                merged[key] = statistics.median(r[key] for r in results)
            elif isinstance(value, dict):
                merged[key] = {k: statistics.median(r[key][k] for r in results) for k in value}
            else:
                merged[key] = value
        out[name] = merged
    out["load"] = (min(loads), max(loads))
    return out


def _clock(args) -> tuple[str, str]:
    """Which time a figure is read from: CPU time on the CPU (what the code costs on a shared box),
    synchronised wall time on a GPU (the CPU thread mostly waits there)."""
    return ("cpu", "CPU") if args.device == "cpu" else ("wall", "wall")


def _on(args) -> str:
    return "" if args.device == "cpu" else f", {args.device}"


def _ratio(new: float, old: float) -> str:
    return f"{old / new:.2f}x" if new > 0 else "-"


def section_step(args, trees) -> list[dict]:
    rows = []
    for n in args.gaussians:
        spec = {"case": "step", "data": str(args.data), "gaussians": n, "steps": args.steps,
                "device": args.device}  # fmt: skip
        res = interleaved(spec, trees, args.rounds)
        clock, unit = _clock(args)
        for name in trees:
            r = res[name]
            r["ratio_cpu"] = r["step_cpu_ms"] / r["raster_cpu_ms"]
            mean = r.get("step_cpu_mean_ms")
            mean_text = "" if mean is None else f", mean {mean:.1f} ms ({mean / r['raster_cpu_ms']:.2f}x)"
            r["ratio"] = r[f"step_{clock}_ms"] / r[f"raster_{clock}_ms"]
            ok = "OK" if r["ratio"] <= STEP_TARGET else "MISSED"
            phases = ", ".join(f"{k} {v:.1f}" for k, v in r["phases_cpu_ms"].items())
            print(
                f"step {n} Gaussians [{name}{_on(args)}]: {r['step_cpu_ms']:.1f} ms CPU "
                f"({r['step_wall_ms']:.1f} ms wall{mean_text}); "
                f"rasterizer fwd+bwd alone {r[f'raster_{clock}_ms']:.1f} ms {unit}; step / rasterizer = "
                f"{r['ratio']:.2f}x {unit} (target <= {STEP_TARGET:g}x: {ok}); "
                f"with the step's two flow channels {r['raster_flow_cpu_ms']:.1f} ms CPU "
                f"(step / that = {r['step_cpu_ms'] / r['raster_flow_cpu_ms']:.2f}x); "
                f"phases (ms {'CPU' if args.device == 'cpu' else 'host wall'}): {phases}; "
                f"load {res['load'][0]:.1f}-{res['load'][1]:.1f}",
                flush=True,
            )
        if "baseline" in trees:
            print(
                f"step {n}: this tree {_ratio(res['new']['step_cpu_ms'], res['baseline']['step_cpu_ms'])} "
                "faster than the baseline (CPU time)",
                flush=True,
            )
        rows.append({"gaussians": n, **res})
    return rows


def quality_verdict(delta: float, delta_pose: float, tolerance: float = 0.1) -> str:
    """A faster step must not cost quality; one that scores higher is not a miss (it is
    reported as better, so a reader knows the result did change)."""
    worst, best = min(delta, delta_pose), max(delta, delta_pose)
    if worst < -tolerance:
        return "MISSED"
    return "OK, better" if best > tolerance else "OK"


def section_quality(args, trees) -> dict:
    spec = {"case": "quality", "data": str(args.data), "scale": args.quality_scale}
    res = interleaved(spec, trees, 1)  # training is deterministic: one run per tree
    for name in trees:
        r = res[name]
        print(
            f"quality [{name}]: fast preset, {args.quality_scale} scale ({r['iterations']} steps, "
            f"{r['gaussians']} Gaussians at the end): novel views PSNR {r['psnr']:.3f} dB, SSIM "
            f"{r['ssim']:.5f}; novel poses PSNR {r['pose_psnr']:.3f} dB, SSIM {r['pose_ssim']:.5f}; "
            f"training {r['train_cpu_s']:.1f} s CPU; "
            f"load {res['load'][0]:.1f}-{res['load'][1]:.1f}",
            flush=True,
        )
    if "baseline" in trees:
        new, old = res["new"], res["baseline"]
        delta = new["psnr"] - old["psnr"]
        delta_pose = new["pose_psnr"] - old["pose_psnr"]
        ok = quality_verdict(delta, delta_pose)
        print(
            f"quality: this tree {delta:+.3f} dB (novel views), {delta_pose:+.3f} dB (novel poses) "
            f"against the baseline (target no more than 0.1 dB below: {ok}); "
            f"training CPU time {_ratio(new['train_cpu_s'], old['train_cpu_s'])} faster",
            flush=True,
        )
    return res


def section_render(args, trees) -> list[dict]:
    rows = []
    for n in args.gaussians:
        spec = {
            "case": "render",
            "data": str(args.data),
            "gaussians": n,
            "size": 512,
            "frames": 60,
            "passes": 1,
            "device": args.device,
        }
        exact = interleaved({**spec, "mode": "exact"}, trees, args.rounds)
        streamed = interleaved({**spec, "mode": "stream"}, {"new": trees["new"]}, args.rounds)
        base = exact.get("baseline")
        cases = [("exact", exact["new"]), ("stream (colour every 2nd frame)", streamed["new"])]
        if base is not None:
            cases.append(("baseline", base))
        target = RENDER_TARGETS.get(n)
        clock, unit = _clock(args)
        for label, r in cases:
            fps = 1e3 / r[f"{clock}_ms"]
            verdict = "" if target is None or label == "baseline" else (" OK" if fps >= target else " MISSED")
            vs = (
                f", {_ratio(r['cpu_ms'], base['cpu_ms'])} the baseline"
                if base and label != "baseline"
                else ""
            )
            print(
                f"render 512x512 {n} Gaussians [{label}{_on(args)}]: {r['cpu_ms']:.1f} ms CPU, "
                f"{r['wall_ms']:.1f} ms wall = {fps:.1f} FPS ({unit}){vs}; target >= {target} FPS{verdict}; "
                f"rasterizer alone {r[f'raster_{clock}_ms']:.1f} ms {unit}; "
                f"load {exact['load'][0]:.1f}-{exact['load'][1]:.1f}",
                flush=True,
            )
        rows.append({"gaussians": n, "exact": exact, "stream": streamed})
    return rows


def section_extremes(args, trees) -> list[dict]:
    rows = []
    cases = [*EXTREME_RENDERS] + ([] if args.no_million else [MILLION])
    for label, n, size in cases:
        frames = 3 if n >= 1_000_000 else 20
        spec = {"case": "render", "data": str(args.data), "gaussians": n, "size": size, "frames": frames,
                "passes": 1, "mode": "exact"}  # fmt: skip
        res = interleaved(spec, trees, args.rounds)
        rows.append({"case": label, **res})
        _print_extreme(f"render {label}", res)
    spec = {"case": "step", "data": str(args.data), "gaussians": 20_000, "steps": 20, "size": 64}
    res = interleaved(spec, trees, args.rounds)
    rows.append({"case": "step at 64x64", **res})
    new, base = res["new"], res.get("baseline")
    vs = (
        f", {_ratio(new['step_cpu_ms'], base['step_cpu_ms'])} the baseline ({base['step_cpu_ms']:.1f} ms)"
        if base
        else ""
    )
    print(f"extreme step 20k at 64x64: {new['step_cpu_ms']:.1f} ms CPU{vs}", flush=True)
    return rows


def _print_extreme(label: str, res: dict) -> None:
    new, base = res["new"], res.get("baseline")
    vs = f", {_ratio(new['cpu_ms'], base['cpu_ms'])} the baseline ({base['cpu_ms']:.1f} ms)" if base else ""
    slower = " SLOWER" if base and new["cpu_ms"] > 1.05 * base["cpu_ms"] else ""
    print(
        f"extreme {label}: {new['cpu_ms']:.1f} ms CPU{vs}{slower}; "
        f"load {res['load'][0]:.1f}-{res['load'][1]:.1f}",
        flush=True,
    )


def bench_ssim(repeats: int) -> dict:
    """SSIM loss forward+backward on a 420x200 crop: the C++ kernel the loss uses on CPU float32
    (image_ops.ssim, analytic backward) against the torch implementation it replaced (and keeps as
    the fallback) and kornia's ssim_loss, in the same run."""
    import kornia
    import torch

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
        out[name] = _timed(lambda fn=fn: (1 - fn(a, b)).backward(), repeats, warmup=3)["wall_ms"]
    with torch.no_grad():
        values = {name: float(fn(a, b)) for name, fn in contenders.items()}
    out["agree"] = max(abs(values["kernel"] - values[k]) for k in ("torch", "kornia"))
    out["torch_over_kernel"] = out["torch"] / out["kernel"]
    out["kornia_over_kernel"] = out["kornia"] / out["kernel"]
    return out


def bench_skip(data: Path, gaussians: int, repeats: int) -> list[dict]:
    """The zero-motion skip (spacetime terms evaluated only on moving rows) against evaluating every
    row, against the rigid part alone (LBS) and against the bare rasterizer; the cases alternate
    render by render."""
    import torch

    from stg_node.avatar import Trainer, TrainFrame
    from stg_node.avatar.data_spec import DataSpec
    from stg_node.avatar.gaussians import MOTION_COLUMNS
    from stg_node.avatar.model import BodyState, Camera3, render
    from stg_node.avatar.nonrigid import rigid_part

    sample = DataSpec(str(data), "synthetic").open("train")[0]
    trainer = Trainer(_balanced(gaussians), seed=0)
    trainer.add_frame(TrainFrame.from_sample(sample))
    model = trainer.model
    table = model.table
    gen = torch.Generator().manual_seed(0)
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
    rows = []
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
        runs = {name: [] for name in cases}
        for _ in range(repeats + 2):
            for name, case in cases.items():
                t = time.thread_time()
                with torch.no_grad():
                    case()
                runs[name].append(time.thread_time() - t)
        rows.append(
            {"gaussians": table.num, "active_fraction": fraction}
            | {name: 1e3 * statistics.median(times[2:]) for name, times in runs.items()}
        )
    return rows


def bench_streams(data: Path, steps: int = 300) -> list[dict]:
    """Streamed colours against exact ones on a briefly trained model (see the module docstring)."""
    import numpy as np

    from stg_node.avatar import AvatarRenderer, Trainer, preset
    from stg_node.avatar.data_spec import DataSpec

    train = DataSpec(str(data), "synthetic").open("train")
    trainer = Trainer(preset("fast").replace(iterations=steps), seed=0)
    trainer.add_frames([train[i] for i in range(0, len(train), 2)])
    for _ in range(steps):
        trainer.step()
    frames = [train[i] for i in range(40, min(len(train), 70))]
    exact = AvatarRenderer(trainer.model)
    truth = [exact.render(f.camera, f.smpl, time=f.time).image.astype(np.float64) for f in frames]
    rows = []
    for every in (2, 3, 4):
        streamed = AvatarRenderer(trainer.model, color_refresh_every=every)
        psnr, worst = [], 0
        for frame, want in zip(frames, truth, strict=True):
            got = streamed.render(frame.camera, frame.smpl, time=frame.time, stream="bench").image
            diff = got.astype(np.float64) - want
            psnr.append(10 * np.log10(255.0**2 / max(float(np.mean(diff**2)), 1e-10)))
            worst = max(worst, int(np.abs(diff).max()))
        rows.append(
            {
                "every": every,
                "psnr_min": min(psnr[1:]),
                "psnr_median": float(np.median(psnr[1:])),
                "worst": worst,
            }
        )
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=None, help="an stg-synth folder (default: generated once in /tmp)")
    parser.add_argument(
        "--baseline", default=BASELINE_REV, help=f"git revision to compare with (default {BASELINE_REV})"
    )
    parser.add_argument("--no-baseline", action="store_true", help="time this tree only")
    parser.add_argument("--rounds", type=int, default=3, help="children per tree and case, alternating")
    parser.add_argument("--steps", type=int, default=40, help="training steps timed per child")
    parser.add_argument("--repeats", type=int, default=20, help="ssim and skip repetitions")
    parser.add_argument("--gaussians", type=int, nargs="+", default=[20000, 50000])
    parser.add_argument(
        "--only", nargs="*", choices=("step", "render", "extremes", "ssim", "skip", "streams", "quality")
    )
    parser.add_argument(
        "--quality-scale", default="mid", choices=("mid", "quick"), help="quality: tradeoff.py's scale"
    )
    parser.add_argument(
        "--no-million", action="store_true", help="extremes: leave out the 1M-Gaussian render"
    )
    parser.add_argument(
        "--device",
        default="cpu",
        choices=("cpu", "cuda"),
        help="cuda: the step and render cases on the GPU with the cuda backend, this tree only",
    )
    parser.add_argument("--json", type=Path, help="also write the results here")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--root", default=str(ROOT), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        run_worker(args.worker, args.root)
        return 0
    sys.path.insert(0, str(ROOT))
    from stg_node.signals import interrupt_on_signals

    # SIGTERM (a time limit) raises here like Ctrl-C, so the child being measured is stopped too:
    # left running, it would load the machine under whatever is measured next
    try:
        with interrupt_on_signals():
            return run_sections(args)
    except KeyboardInterrupt:
        print("bench: stopped (the rows above are complete; the child being measured was stopped)",
              file=sys.stderr, flush=True)  # fmt: skip
        return 130


def run_sections(args) -> int:
    from stg_node.threads import configure_threads

    configure_threads("1")
    args.data = ensure_data(args.data)
    trees = {"new": ROOT}
    if args.device != "cpu":
        args.no_baseline = True  # the baselines are the rasterizer on the same device and the cpu rows
        args.only = [s for s in (args.only or ["step", "render"]) if s in ("step", "render")]
    if not args.no_baseline:
        trees["baseline"] = export_revision(args.baseline)
    tree_list = ", ".join(f"{k} = {v}" for k, v in trees.items())
    print(f"# machine: {_machine()}; device: {_device_name(args.device)}; trees: {tree_list}", flush=True)
    sections = args.only or ["step", "render", "extremes", "ssim", "skip", "streams"]
    results: dict = {"machine": _machine(), "baseline": None if args.no_baseline else args.baseline,
                     "device": _device_name(args.device)}  # fmt: skip
    if "step" in sections:
        results["step"] = section_step(args, trees)
    if "render" in sections:
        results["render"] = section_render(args, trees)
    if "quality" in sections:
        results["quality"] = section_quality(args, trees)
    if "extremes" in sections:
        results["extremes"] = section_extremes(args, trees)
    if "ssim" in sections:
        s = bench_ssim(args.repeats)
        results["ssim"] = s
        print(
            f"ssim fwd+bwd 420x200: C++ kernel {s['kernel']:.2f} ms, torch {s['torch']:.1f} ms, "
            f"kornia {s['kornia']:.1f} ms (torch / kernel = {s['torch_over_kernel']:.1f}x, "
            f"kornia / kernel = {s['kornia_over_kernel']:.1f}x; values agree to {s['agree']:.1e})",
            flush=True,
        )
    if "skip" in sections:
        results["skip"] = []
        for n in args.gaussians:
            for r in bench_skip(args.data, n, args.repeats):
                results["skip"].append(r)
                print(
                    f"skip: render 512x512 {r['gaussians']} Gaussians, "
                    f"{100 * r['active_fraction']:.0f}% moving: {r['ms_skip']:.1f} ms CPU with the "
                    f"zero-motion skip, {r['ms_all']:.1f} ms evaluating every row "
                    f"(x{r['ms_all'] / r['ms_skip']:.2f}); its rigid part alone (LBS) {r['ms_lbs']:.1f} ms "
                    f"(skip / LBS = {r['ms_skip'] / r['ms_lbs']:.2f}x); "
                    f"rasterizer alone {r['ms_raster_only']:.1f} ms",
                    flush=True,
                )
    if "streams" in sections:
        results["streams"] = bench_streams(args.data)
        for r in results["streams"]:
            print(
                f"streams: colours every {r['every']} frames against exact: PSNR {r['psnr_min']:.1f} dB at "
                f"worst, {r['psnr_median']:.1f} dB median, at most {r['worst']} grey level(s) apart",
                flush=True,
            )
    if args.json:
        args.json.write_text(json.dumps(results, indent=2, default=str) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
