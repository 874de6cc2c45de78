#!/usr/bin/env python3
"""The running system's figures: pose-to-pixels latency, snapshot hot-swap pause, memory on a long stream,
live rendering beside the trainer.

Every node runs as its own process under stg-launch's supervisor (a private ipc bus); this tool
watches from outside over the bus.

1. latency: the renderer alone, with a snapshot made by a few training steps on the data. (a)
   one-shot ViewRequests (a pose and a camera in, follow_live false): time from the request's
   publication to the receipt of the RenderedImage that answers it; (b) BodyPoses into a
   standing view: publication of the pose to receipt of the image rendered for it (pose_seq).
   One in flight at a time; median and p95 over --requests. Target: <= 50 ms at 256 x 256.
2. hot swap: the renderer renders a standing view on poses at --swap-rate Hz while a new snapshot
   arrives every 2 s; the pause is the longest gap between images within 0.5 s after a new
   snapshot is published, minus the median gap elsewhere (0 = no hitch).
3. memory: ingest (dataset replay in a loop at --stream-rate Hz, i.e. sped up), tracker, trainer
   and renderer for --stream-s seconds; resident memory (VmRSS) of each process sampled every
   second; the growth over the second half of the run, in MB per hour of stream time.
4. live: the whole pipeline at camera rate: ingest replays the data at --live-rate Hz (30) at
   --live-size (512), the tracker publishes poses, the trainer (fast preset) trains and publishes
   snapshots, and the renderer renders a standing view (the data's camera at --live-size) for
   every pose, beside the trainer. Over --live-s seconds once the first image arrived: images
   rendered per second, poses per second, and frame age (a pose's source stamp to the receipt of
   its image) p50/p95. The trainer runs at niceness --trainer-nice (10, as the live launch
   files set it: the live path first on a shared CPU; 0: as the other nodes); the niceness read
   back from the trainer's process is reported. With --baseline REV the same run is repeated on
   that git revision (tools/baseline.py), alternating, in the same invocation; a revision whose
   launcher has no ``nice`` key runs its trainer as the other nodes (the comparison then shows it).
5. soak (only with ``--only soak``; --soak-s, 30 minutes by default): the live pipeline in real
   time from a video at 30 fps: ingest (the subject's training camera as a looped MP4), tracker
   (live: BlazePose + SMPL fit), online trainer, renderer, and a recorder (zstd) of the whole
   bus, as launch/live_v4l2.yaml runs them, under stg-launch. Measured from outside: each
   process's resident memory every 5 s and its slope after the warm-up (MB per hour; target
   <= +20), the frame age (the time from a frame's capture to the arrival of what came of it:
   body/pose from the tracker, avatar/image from the renderer) p50/p95 over the first and the
   last --soak-window-s of the run (target: the last p95 within 20 % of the first), and the
   backlog of every lossless stream (messages a node has published on a topic that a lossless
   subscriber has not yet taken, from their heartbeats) first vs last window: a queue that
   grows shows there. On a shared machine the frame age follows the CPU the pipeline gets, so
   each window also gives the machine's load average and the cores the pipeline's processes
   used; the JSON keeps the memory and load series.

    python tools/bench_pipeline.py --data runs/demo/subject [--avatar stg_node.avatar] [--json out.json]
    python tools/bench_pipeline.py --data DIR --only live --live-size 512 --baseline 6bbdca2
    python tools/bench_pipeline.py --data DIR --avatar tests.nodes.fake_avatar --quick    # smoke run
    python tools/bench_pipeline.py --data runs/zju_subject --only soak --json soak.json    # 30 minutes

Figures go to docs/BENCHMARKS.md only from an idle machine (the lead's final run).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import textwrap
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if "--root" in sys.argv:  # a child timing another tree (--baseline): import that one's stg_node
    ROOT = Path(sys.argv[sys.argv.index("--root") + 1]).resolve()
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from stg_node.bus import Bus, BusConfig, Subscriber, ViewRequest  # noqa: E402
from stg_node.bus.messages import NodeStatus, RenderedImage  # noqa: E402
from stg_node.launch import read_launch  # noqa: E402
from stg_node.launch.process import OutputSink  # noqa: E402
from stg_node.launch.supervisor import Launcher  # noqa: E402
from stg_node.nodes.convert import pose_message, resized_camera  # noqa: E402


class QuietSink(OutputSink):
    """Node output to a file (the bench prints its own table)."""

    def __init__(self, path: Path):
        self._file = path.open("w")
        super().__init__(self._file, color=False)

    def close(self) -> None:
        super().close()
        self._file.close()


def start_launch(workdir: Path, name: str, nodes_yaml: str) -> tuple[Launcher, threading.Thread, str]:
    url = f"ipc://{workdir}/{name}"
    path = workdir / f"{name}.yaml"
    path.write_text(
        f'bus: {{url: "{url}"}}\nenv: {{STG_THREADS: "1"}}\nnodes:\n' + textwrap.indent(nodes_yaml, "  ")
    )
    launcher = Launcher(read_launch(path), sink=QuietSink(workdir / f"{name}.log"))
    thread = threading.Thread(target=launcher.run, name=f"launch-{name}", daemon=True)
    thread.start()
    return launcher, thread, url


def stop_launch(launcher: Launcher, thread: threading.Thread) -> None:
    launcher.request_stop("bench done")
    thread.join(60)
    launcher.sink.close()


def wait_ready(url: str, names: set[str], timeout: float = 120.0) -> dict[str, int]:
    pids: dict[str, int] = {}
    with Subscriber(BusConfig(url=url), ["node/status"]) as sub:
        deadline = time.monotonic() + timeout
        while not names <= set(pids) and time.monotonic() < deadline:
            msg = sub.recv(timeout=0.5)
            if isinstance(msg, NodeStatus) and msg.state == "running" and msg.node in names:
                pids[msg.node] = msg.pid
    if not names <= set(pids):
        raise SystemExit(f"bench: nodes {sorted(names - set(pids))} did not come up within {timeout:g} s")
    return pids


def make_snapshot(avatar: str, data: str, steps: int, size: int, version: int):
    """A snapshot from ``steps`` training steps on the first frames of ``data`` (the nodes' adapter)."""
    from stg_node.nodes.avatar_adapter import TrainerAdapter
    from stg_node.nodes.sources import DatasetSource

    source = DatasetSource(data, size=size)
    trainer = TrainerAdapter.create(module=avatar, preset="fast")
    first = None
    for i, frame in enumerate(source.frames()):
        first = first or frame
        trainer.add_frame(
            index=frame.index,
            time=frame.time,
            image=frame.image,
            mask=frame.mask,
            camera=frame.camera,
            smpl=source.dataset.smpl(frame.index),
        )
        if i >= 7:
            break
    for _ in range(steps):
        trainer.step()
    return trainer.snapshot(version), first, source.dataset.smpl(first.index)


@contextlib.contextmanager
def renderer_session(args, workdir: Path, name: str):
    """A renderer alone under the launcher; yields (bus to publish on, subscriber of avatar/image)."""
    nodes = f"""
    - name: renderer
      kind: renderer
      params: {{avatar: {args.avatar}, device: {args.device}, default_view: none,
                 idle_rate_hz: 0, max_rate_hz: 1000}}
    """
    launcher, thread, url = start_launch(workdir, name, textwrap.dedent(nodes))
    try:
        wait_ready(url, {"renderer"})
        with (
            Bus(url, node="bench", heartbeat_s=0) as bus,
            Subscriber(BusConfig(url=url), ["avatar/image"]) as images,
        ):
            for topic in ("avatar/snapshot", "avatar/view", "body/pose"):
                bus.publisher.wait_for_subscribers(topic, 30)
            yield bus, images
    finally:
        stop_launch(launcher, thread)


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q)) if values else float("nan")


def bench_latency(args, workdir: Path) -> dict:
    snap, frame, smpl = make_snapshot(args.avatar, args.data, args.train_steps, args.size, 1)
    camera = resized_camera(frame.camera, args.size)
    oneshot, live = [], []
    with renderer_session(args, workdir, "latency") as (bus, images):
        bus.publish(snap)
        pose = pose_message(smpl)
        request = ViewRequest(
            request_id=0,
            width=camera.width,
            height=camera.height,
            follow_live=False,
            K=camera.K,
            R=camera.R,
            t=camera.t,
            poses=pose.poses,
            Rh=pose.Rh,
            Th=pose.Th,
        )
        total = args.requests + 5
        for i in range(total):  # (a) one-shot requests
            request.request_id = i + 1
            sent = time.time_ns()
            bus.publish(request, stamp_ns=sent)
            while (msg := images.recv(timeout=10)) is not None and msg.request_id != i + 1:
                pass
            if msg is None:
                raise SystemExit("bench: no answer to a view request within 10 s")
            if i >= 5:  # warm-up
                oneshot.append((time.time_ns() - sent) / 1e6)
        standing = ViewRequest(
            request_id=10_000,
            width=camera.width,
            height=camera.height,
            follow_live=True,
            K=camera.K,
            R=camera.R,
            t=camera.t,
        )
        bus.publish(standing)
        time.sleep(0.5)
        for i in range(total):  # (b) poses into the standing view
            sent = time.time_ns()
            seq = bus.publish(pose, stamp_ns=sent)
            while (msg := images.recv(timeout=10)) is not None and msg.pose_seq != seq:
                pass
            if msg is None:
                raise SystemExit("bench: no image for a pose within 10 s")
            if i >= 5:
                live.append((time.time_ns() - sent) / 1e6)
            time.sleep(0.01)
    return {
        "size": [camera.width, camera.height],
        "request_ms_median": statistics.median(oneshot),
        "request_ms_p95": percentile(oneshot, 95),
        "pose_ms_median": statistics.median(live),
        "pose_ms_p95": percentile(live, 95),
        "samples": len(oneshot),
    }


def bench_swap(args, workdir: Path) -> dict:
    snaps = [make_snapshot(args.avatar, args.data, args.train_steps, args.size, v)[0] for v in (1, 2)]
    _, frame, smpl = make_snapshot(args.avatar, args.data, 1, args.size, 0)
    camera = resized_camera(frame.camera, args.size)
    arrivals: list[float] = []
    swaps: list[float] = []
    with renderer_session(args, workdir, "swap") as (bus, images):
        bus.publish(snaps[0])
        bus.publish(
            ViewRequest(
                request_id=1, width=camera.width, height=camera.height, K=camera.K, R=camera.R, t=camera.t
            )
        )
        pose = pose_message(smpl)
        period = 1.0 / args.swap_rate
        start = time.monotonic()
        next_swap = start + 2.0
        version = 1
        stop = threading.Event()

        def collect():
            while not stop.is_set():
                msg = images.recv(timeout=0.1)
                if isinstance(msg, RenderedImage):
                    arrivals.append(time.monotonic())

        reader = threading.Thread(target=collect, daemon=True)
        reader.start()
        while time.monotonic() - start < args.swap_s:
            bus.publish(pose, stamp_ns=time.time_ns())
            if time.monotonic() >= next_swap:
                version += 1
                snap = snaps[version % 2]
                snap.model_version = version
                bus.publish(snap)
                swaps.append(time.monotonic())
                next_swap += 2.0
            time.sleep(period)
        stop.set()
        reader.join(2)
    times = np.asarray(arrivals)
    gaps = np.diff(times)
    near = np.zeros(len(gaps), bool)
    for s in swaps:
        near |= (times[1:] > s) & (times[:-1] < s + 0.5)
    base = float(np.median(gaps[~near])) if (~near).any() else float("nan")
    worst = float(gaps[near].max()) if near.any() else float("nan")
    return {
        "swaps": len(swaps),
        "median_gap_ms": base * 1e3,
        "worst_gap_near_swap_ms": worst * 1e3,
        "pause_ms": max(0.0, worst - base) * 1e3,
        "images": len(arrivals),
    }


def cpu_s(pid: int) -> float:
    """CPU seconds (user + system) a process has used so far; NaN once it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime
    except (OSError, IndexError, ValueError):
        return float("nan")


def rss_mb(pid: int) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def bench_memory(args, workdir: Path) -> dict:
    nodes = f"""
    - name: tracker
      kind: tracker
      params: {{path: {args.data}}}
    - name: trainer
      kind: trainer
      params: {{avatar: {args.avatar}, device: {args.device}, preset: fast,
                 max_frames: 64, snapshot_every_s: 5}}
    - name: renderer
      kind: renderer
      params: {{avatar: {args.avatar}, device: {args.device}, size: {args.size}}}
    - name: ingest
      kind: ingest
      params: {{path: {args.data}, size: {args.size}, rate_hz: {args.stream_rate}, loop: true}}
      after: [tracker, trainer]
    """
    launcher, thread, url = start_launch(workdir, "memory", textwrap.dedent(nodes))
    samples: dict[str, list[tuple[float, float]]] = {}
    try:
        pids = wait_ready(url, {"ingest", "tracker", "trainer", "renderer"})
        start = time.monotonic()
        while (elapsed := time.monotonic() - start) < args.stream_s:
            for name, pid in pids.items():
                samples.setdefault(name, []).append((elapsed, rss_mb(pid)))
            time.sleep(1.0)
    finally:
        stop_launch(launcher, thread)
    speedup = args.stream_rate / 30.0  # stream seconds per wall second, for a 30 fps camera
    out = {"stream_minutes": args.stream_s * speedup / 60, "nodes": {}}
    for name, points in samples.items():
        t, mb = np.array(points).T
        half = t >= t[-1] / 2
        slope = (
            float(np.polyfit(t[half], mb[half], 1)[0]) if half.sum() >= 2 else float("nan")
        )  # MB per wall s
        out["nodes"][name] = {
            "start_mb": float(mb[0]),
            "end_mb": float(mb[-1]),
            "peak_mb": float(np.nanmax(mb)),
            "mb_per_stream_hour": slope * 3600 / speedup,
        }
    return out


def bench_live(args, workdir: Path) -> dict:
    from stg_node.nodes.sources import DatasetSource

    first = next(iter(DatasetSource(args.data, size=args.live_size).frames()))
    camera = resized_camera(first.camera, args.live_size)
    nice = trainer_nice_key(args.trainer_nice)
    nodes = f"""
    - name: tracker
      kind: tracker
      params: {{path: {args.data}}}
    - name: trainer
      kind: trainer
      params: {{avatar: {args.avatar}, device: {args.device}, preset: fast,
                 max_frames: 64, snapshot_every_s: 5}}{nice}
    - name: renderer
      kind: renderer
      params: {{avatar: {args.avatar}, device: {args.device}, default_view: none, idle_rate_hz: 0}}
    - name: ingest
      kind: ingest
      params: {{path: {args.data}, size: {args.live_size}, rate_hz: {args.live_rate}, loop: true}}
      after: [tracker, trainer]
    """
    launcher, thread, url = start_launch(workdir, "live", textwrap.dedent(nodes))
    ages, render_ms, arrivals, poses = [], [], [], []
    try:
        wait_ready(url, {"ingest", "tracker", "trainer", "renderer"})
        trainer_nice = process_nice(launcher, "trainer")
        with (
            Bus(url, node="bench", heartbeat_s=0) as bus,
            Subscriber(BusConfig(url=url), ["avatar/image", "body/pose"]) as sub,
        ):
            bus.publisher.wait_for_subscribers("avatar/view", 30)
            view = ViewRequest(
                request_id=1, width=camera.width, height=camera.height, follow_live=True,
                K=camera.K, R=camera.R, t=camera.t,
            )  # fmt: skip
            bus.publish(view)
            deadline = time.monotonic() + args.live_warmup_s
            while not isinstance(sub.recv(timeout=0.5), RenderedImage):  # the first snapshot is in
                if time.monotonic() > deadline:
                    raise SystemExit(
                        f"bench: no image within {args.live_warmup_s:g} s (see {workdir}/live.log)"
                    )
            settle = time.monotonic() + 5.0
            while time.monotonic() < settle:
                sub.recv(timeout=0.1)
            start = time.monotonic()
            while time.monotonic() - start < args.live_s:
                msg = sub.recv(timeout=0.5)
                now_ns = time.time_ns()
                if isinstance(msg, RenderedImage):
                    arrivals.append(time.monotonic())
                    render_ms.append(msg.render_ms)
                    if msg.source_stamp_ns:
                        ages.append((now_ns - msg.source_stamp_ns) / 1e6)
                elif msg is not None:
                    poses.append(time.monotonic())
            duration = time.monotonic() - start
    finally:
        stop_launch(launcher, thread)
    if not arrivals:
        raise SystemExit(f"bench: no image in {args.live_s:g} s of the live run (see {workdir}/live.log)")
    return {
        "size": [camera.width, camera.height],
        "camera_hz": args.live_rate,
        "seconds": duration,
        "images_per_s": len(arrivals) / duration,
        "poses_per_s": len(poses) / duration,
        "age_ms_p50": percentile(ages, 50),
        "age_ms_p95": percentile(ages, 95),
        "render_ms_p50": percentile(render_ms, 50),
        "render_ms_p95": percentile(render_ms, 95),
        "trainer_nice": trainer_nice,
    }


def trainer_nice_key(nice: int) -> str:
    """The trainer's ``nice:`` launch key (indented for a node block), or nothing where this tree's
    launcher has none (an older revision timed with --baseline) or ``nice`` is 0."""
    from stg_node.launch.spec import NodeEntry

    if nice == 0 or "nice" not in {f.name for f in dataclasses.fields(NodeEntry)}:
        return ""
    return f"\n      nice: {nice}"


def process_nice(launcher: Launcher, name: str) -> int | None:
    """The niceness of a launched node's process, read back from the system (None: not running)."""
    for state in launcher.states:
        if state.spec.name == name and state.proc is not None and state.proc.popen is not None:
            try:
                return os.getpriority(os.PRIO_PROCESS, state.proc.popen.pid)
            except OSError:
                return None
    return None


def live_with_baseline(args) -> dict:
    """The live run on this tree and on ``args.baseline``, alternating, each in a child process
    that imports its own tree (and launches its nodes from it)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from baseline import child_env, export_revision

    trees = {"new": Path(__file__).resolve().parents[1], "baseline": export_revision(args.baseline)}
    out: dict[str, list] = {name: [] for name in trees}
    names = list(trees)
    for r in range(args.rounds):
        for name in names if r % 2 == 0 else names[::-1]:
            cmd = [sys.executable, str(Path(__file__).resolve()), "--root", str(trees[name]), "--live-child"]
            cmd += [
                "--data",
                str(Path(args.data).resolve()),
                "--avatar",
                args.avatar,
                "--device",
                args.device,
            ]
            cmd += ["--live-s", str(args.live_s), "--live-rate", str(args.live_rate)]
            cmd += ["--live-size", str(args.live_size), "--live-warmup-s", str(args.live_warmup_s)]
            cmd += ["--trainer-nice", str(args.trainer_nice)]
            env = child_env(trees[name])
            done = subprocess.run(cmd, env=env, cwd=trees[name], capture_output=True, text=True)
            if done.returncode != 0:
                raise SystemExit(f"bench: the live child on {trees[name]} failed:\n{done.stderr[-4000:]}")
            result = json.loads(done.stdout.strip().splitlines()[-1])
            result["load"] = os.getloadavg()[0]
            out[name].append(result)
            print(f"live [{name}]: {json.dumps(result)}", flush=True)
    return out


# --- soak: the live pipeline in real time ------------------------------------------------------------


def make_clip(data: str, folder: Path, fps: float = 30.0) -> tuple[Path, Path]:
    """The training camera of ``data`` as an MP4 at ``fps`` and its calibration JSON (K, R, t)."""
    import cv2

    from stg_node.nodes.sources import DatasetSource

    source = DatasetSource(data, size=None)
    first = source.views[0].camera
    video, calibration = folder / "clip.mp4", folder / "camera.json"
    writer = None
    camera = None
    for frame in source.frames():
        if frame.camera.name != first:
            continue
        if writer is None:
            camera = frame.camera
            h, w = frame.image.shape[:2]
            writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
        writer.write(np.ascontiguousarray(frame.image[..., ::-1]))  # OpenCV writes BGR
    writer.release()
    calibration.write_text(
        json.dumps({"K": camera.K.tolist(), "R": camera.R.tolist(), "t": np.ravel(camera.t).tolist()})
    )
    return video, calibration


def soak_launch(args, workdir: Path, video: Path, calibration: Path) -> Path:
    """The nodes of launch/live_v4l2.yaml (source:=video), the recorder compressed."""
    path = workdir / "soak.yaml"
    path.write_text(
        textwrap.dedent(
            f"""
            bus: {{url: "ipc://{workdir}/soak"}}
            env: {{STG_THREADS: "1"}}
            nodes:
              - name: recorder
                kind: recorder
                params: {{path: {workdir}/soak.mcap, compression: zstd}}
                sigint_timeout: 60
              - name: tracker
                kind: tracker
                params: {{mode: live, input_topic: raw/camera/frame, frame_topic: camera/frame,
                          estimator_params: {{max_side: "512", mask: segmentation}}}}
              - name: trainer
                kind: trainer
                params: {{avatar: {args.avatar}, preset: fast, device: {args.device}, snapshot_every_s: 5,
                          checkpoint_dir: {workdir}/checkpoint, out: {workdir}/out}}
                sigint_timeout: 60
                nice: {args.trainer_nice}
              - name: renderer
                kind: renderer
                params: {{avatar: {args.avatar}, device: {args.device}}}
              - name: ingest
                kind: ingest
                params: {{source: video, path: {video}, calibration: {calibration}, loop: true}}
                remap: {{camera/frame: raw/camera/frame}}
                after: [tracker, trainer, recorder]
            """
        )
    )
    return path


class SoakWatch:
    """Heartbeats, poses and images as they arrive (with when), in a thread."""

    def __init__(self, url: str):
        self.sub = Subscriber(BusConfig(url=url), ["node/status", "body/pose", "avatar/image"])
        self.lock = threading.Lock()
        self.status: dict[str, NodeStatus] = {}
        self.backlog: list[tuple[float, dict[str, int]]] = []  # (t, stream -> messages not yet taken)
        self.pose_age: list[tuple[float, float]] = []  # (t, ms from capture to arrival)
        self.image_age: list[tuple[float, float]] = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def run(self) -> None:
        from stg_node.bus.messages import BodyPose

        while not self.stop.is_set():
            msg = self.sub.recv(timeout=0.2)
            now, wall = time.monotonic(), time.time_ns()
            with self.lock:
                if isinstance(msg, NodeStatus):
                    self.status[msg.node] = msg
                    self.backlog.append((now, self._backlog()))
                elif isinstance(msg, BodyPose):
                    self.pose_age.append((now, (wall - msg.header.stamp_ns) / 1e6))
                elif isinstance(msg, RenderedImage) and msg.source_stamp_ns:
                    self.image_age.append((now, (wall - msg.source_stamp_ns) / 1e6))

    LOSSLESS = {"trainer": ("body/pose",), "recorder": ("body/pose", "trainer/metrics", "avatar/snapshot")}

    def _backlog(self) -> dict[str, int]:
        """Per lossless stream (a topic into a subscriber that takes every message of it): what
        every node has published on it minus what the subscriber has taken, from their latest
        heartbeats (which are up to a period apart: a steady backlog of about a second's worth of
        messages is in flight; one that grows is a queue). Keep-last topics (frames, images) and
        heartbeats (which the broker sends too) are left out."""
        out = {}
        for sub_name, topics in self.LOSSLESS.items():
            sub = self.status.get(sub_name)
            if sub is None:
                continue
            for topic in topics:
                published = sum(s.published.get(topic, 0) for s in self.status.values())
                out[f"{topic} -> {sub_name}"] = max(0, published - sub.received.get(topic, 0))
        return out

    def close(self) -> None:
        self.stop.set()
        self.thread.join(2)
        self.sub.close()


def window_stats(samples: list[tuple[float, float]], start: float, end: float) -> dict:
    values = [v for t, v in samples if start <= t < end]
    return {"n": len(values), "p50_ms": percentile(values, 50), "p95_ms": percentile(values, 95)}


def machine_stats(samples: list[tuple[float, float, float]], start: float, end: float) -> dict:
    """Mean load average and the cores the pipeline's processes used (CPU seconds per second)
    between ``start`` and ``end`` (seconds into the soak)."""
    inside = [(t, load, cpu) for t, load, cpu in samples if start <= t <= end]
    if len(inside) < 2:
        return {"load_avg": float("nan"), "pipeline_cores": float("nan")}
    (t0, _l, c0), (t1, _l1, c1) = inside[0], inside[-1]
    return {
        "load_avg": statistics.fmean(load for _t, load, _c in inside),
        "pipeline_cores": (c1 - c0) / (t1 - t0) if t1 > t0 else float("nan"),
    }


def bench_soak(args, workdir: Path) -> dict:
    import signal
    import subprocess

    video, calibration = make_clip(args.data, workdir)
    path = soak_launch(args, workdir, video, calibration)
    log = (workdir / "soak.log").open("w")
    launcher = subprocess.Popen(
        [sys.executable, "-m", "stg_node.cli.launch", str(path), "--no-color"],
        cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
    )  # fmt: skip
    url = f"ipc://{workdir}/soak"
    watch = SoakWatch(url)
    memory: dict[str, list[tuple[float, float]]] = {}
    machine: list[tuple[float, float, float]] = []  # (t, 1-minute load average, the pipeline's CPU seconds)
    try:
        pids = wait_ready(url, {"ingest", "tracker", "trainer", "renderer", "recorder"}, timeout=600)
        pids["launcher+broker"] = launcher.pid
        deadline = time.monotonic() + 600  # the pipeline is up when the avatar shows
        while not watch.image_age and time.monotonic() < deadline:
            time.sleep(1.0)
        if not watch.image_age:
            raise SystemExit(
                f"bench: no avatar/image within 600 s of the soak's start; see {workdir / 'soak.log'}"
            )
        start = time.monotonic()
        next_report = start + 60
        while (now := time.monotonic()) < start + args.soak_s:
            for name, pid in pids.items():
                memory.setdefault(name, []).append((now - start, rss_mb(pid)))
            machine.append((now - start, os.getloadavg()[0], sum(cpu_s(pid) for pid in pids.values())))
            if now >= next_report:
                rss = ", ".join(f"{n} {pts[-1][1]:.0f}" for n, pts in memory.items())
                print(f"soak: {(now - start) / 60:.0f} min, RSS MB: {rss}", flush=True)
                next_report += 60
            if launcher.poll() is not None:
                raise SystemExit(f"bench: the soak's launch ended early; see {workdir / 'soak.log'}")
            time.sleep(5.0)
        end = time.monotonic()
    finally:
        if launcher.poll() is None:
            launcher.send_signal(signal.SIGINT)
            try:
                launcher.wait(300)
            except subprocess.TimeoutExpired:
                launcher.kill()
        watch.close()
        log.close()
    w = args.soak_window_s
    first, last = (start, start + w), (end - w, end)
    out = {
        "minutes": (end - start) / 60,
        "warmup_minutes": args.soak_warmup_s / 60,
        "window_minutes": w / 60,
        "memory": {},
        "pose_age": {
            "first": window_stats(watch.pose_age, *first),
            "last": window_stats(watch.pose_age, *last),
        },
        "image_age": {
            "first": window_stats(watch.image_age, *first),
            "last": window_stats(watch.image_age, *last),
        },
        "backlog": {},
        # what the machine gave the pipeline in each window: frame age on a shared machine follows it
        "machine": {
            "first": machine_stats(machine, 0.0, w),
            "last": machine_stats(machine, end - start - w, end - start),
        },
        "series": {
            "t_s": [t for t, _l, _c in machine],
            "load_avg": [load for _t, load, _c in machine],
            "rss_mb": {name: [mb for _t, mb in points] for name, points in memory.items()},
        },
        "status": {
            n: {"drops": dict(s.drops), "published": dict(s.published), "received": dict(s.received)}
            for n, s in watch.status.items()
        },
    }
    for name, points in memory.items():
        t, mb = np.array(points).T
        after = t >= args.soak_warmup_s
        slope = float(np.polyfit(t[after], mb[after], 1)[0]) * 3600 if after.sum() >= 2 else float("nan")
        out["memory"][name] = {
            "at_warmup_mb": float(mb[after][0]) if after.any() else float("nan"),
            "end_mb": float(mb[-1]),
            "peak_mb": float(np.nanmax(mb)),
            "mb_per_hour": slope,
        }
    streams = sorted({k for _t, b in watch.backlog for k in b})
    for stream in streams:
        firsts = [b[stream] for t, b in watch.backlog if first[0] <= t < first[1] and stream in b]
        lasts = [b[stream] for t, b in watch.backlog if last[0] <= t < last[1] and stream in b]
        out["backlog"][stream] = {
            "first_median": statistics.median(firsts) if firsts else None,
            "last_median": statistics.median(lasts) if lasts else None,
            "last_max": max(lasts) if lasts else None,
        }
    for kind in ("pose_age", "image_age"):
        a, b = out[kind]["first"]["p95_ms"], out[kind]["last"]["p95_ms"]
        out[kind]["last_over_first_p95"] = b / a if a and a == a and b == b else float("nan")
    return out


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--data", required=True, help="a dataset folder (e.g. stg-synth output) to train and stream from"
    )
    parser.add_argument(
        "--avatar", default="stg_node.avatar", help="the avatar implementation (package name)"
    )
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--size", type=int, default=256, help="image size (longer side)")
    parser.add_argument("--train-steps", type=int, default=200, help="steps before the latency snapshot")
    parser.add_argument("--requests", type=int, default=100, help="latency samples per kind")
    parser.add_argument("--swap-s", type=float, default=20.0, help="seconds of the hot-swap run")
    parser.add_argument(
        "--swap-rate", type=float, default=30.0, help="poses per second during the hot-swap run"
    )
    parser.add_argument("--stream-s", type=float, default=360.0, help="wall seconds of the memory run")
    parser.add_argument(
        "--stream-rate", type=float, default=300.0, help="frames per second of the sped-up stream"
    )
    parser.add_argument("--live-s", type=float, default=60.0, help="seconds measured in the live run")
    parser.add_argument("--live-rate", type=float, default=30.0, help="camera rate of the live run (Hz)")
    parser.add_argument("--live-size", type=int, default=512, help="image size of the live run (longer side)")
    parser.add_argument(
        "--live-warmup-s",
        type=float,
        default=120.0,
        help="live run: wait at most this long for the first image",
    )
    parser.add_argument(
        "--baseline", help="live run: also time this git revision, alternating (tools/baseline.py)"
    )
    parser.add_argument("--rounds", type=int, default=1, help="live run with --baseline: runs per tree")
    parser.add_argument(
        "--trainer-nice",
        type=int,
        default=10,
        help="live and soak: the trainer's CPU niceness (the live launch files' 10; 0: as the other nodes)",
    )
    parser.add_argument("--root", help=argparse.SUPPRESS)
    parser.add_argument("--live-child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument(
        "--only",
        choices=("latency", "swap", "memory", "live", "soak"),
        action="append",
        help="run only these",
    )
    parser.add_argument("--soak-s", type=float, default=1800.0, help="seconds of the soak (after warm-up)")
    parser.add_argument("--soak-warmup-s", type=float, default=300.0, help="memory slope only after this")
    parser.add_argument("--soak-window-s", type=float, default=300.0, help="first/last windows compared")
    parser.add_argument("--quick", action="store_true", help="a smoke run: few samples, short runs")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args()
    if args.quick:
        args.train_steps, args.requests, args.swap_s, args.stream_s = 5, 10, 5.0, 8.0
        args.live_s = min(args.live_s, 10.0)
        args.soak_s, args.soak_warmup_s, args.soak_window_s = 60.0, 20.0, 20.0
    os.environ.setdefault("STG_THREADS", "1")
    if args.live_child:
        with tempfile.TemporaryDirectory(prefix="stgbench-") as tmp:
            print(json.dumps(bench_live(args, Path(tmp))), flush=True)
        return 0
    if args.baseline and (args.only or []) == ["live"]:
        results = live_with_baseline(args)
        _print_live(results)
        if args.json:
            args.json.write_text(json.dumps(results, indent=2) + "\n")
        return 0
    results = {
        "machine": f"{platform.node()} {platform.machine()} {os.cpu_count()} cpus",
        "avatar": args.avatar,
    }
    with tempfile.TemporaryDirectory(prefix="stgbench-") as tmp:
        workdir = Path(tmp)
        benches = (
            ("latency", bench_latency),
            ("swap", bench_swap),
            ("memory", bench_memory),
            ("live", bench_live),
            ("soak", bench_soak),
        )
        for name, fn in benches:
            if (args.only and name not in args.only) or (
                name == "soak" and not (args.only and "soak" in args.only)
            ):
                continue  # (the soak runs only when asked for: it takes half an hour)
            results[name] = fn(args, workdir)
            print(f"{name}: {json.dumps(results[name], indent=None)}", flush=True)
    lat = results.get("latency")
    if lat:
        ok = "meets" if lat["request_ms_median"] <= 50 else "misses"
        print(
            f"pose-to-pixels at {lat['size'][0]}x{lat['size'][1]}: request {lat['request_ms_median']:.1f} ms "
            f"(p95 {lat['request_ms_p95']:.1f}), pose {lat['pose_ms_median']:.1f} ms: {ok} the 50 ms target"
        )
    if "live" in results:
        _print_live({"new": [results["live"]]})
    soak = results.get("soak")
    if soak:
        for name, m in soak["memory"].items():
            mb = f"{m['at_warmup_mb']:7.0f} -> {m['end_mb']:7.0f} MB"
            print(f"soak memory {name:16s} {mb}, {m['mb_per_hour']:+7.1f} MB/h")
        for kind in ("pose_age", "image_age"):
            a, b = soak[kind]["first"], soak[kind]["last"]
            ratio = soak[kind]["last_over_first_p95"]
            print(
                f"soak {kind}: p95 {a['p95_ms']:.0f} -> {b['p95_ms']:.0f} ms (x{ratio:.2f}), "
                f"p50 {a['p50_ms']:.0f} -> {b['p50_ms']:.0f} ms, {a['n']} / {b['n']} samples"
            )
        a, b = soak["machine"]["first"], soak["machine"]["last"]
        print(
            f"soak machine: load average {a['load_avg']:.1f} -> {b['load_avg']:.1f}, "
            f"the pipeline's processes used {a['pipeline_cores']:.2f} -> {b['pipeline_cores']:.2f} cores"
        )
        for stream, q in soak["backlog"].items():
            print(f"soak backlog {stream}: {q['first_median']} -> {q['last_median']} (max {q['last_max']})")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")
    return 0


def _print_live(results: dict) -> None:
    for name, runs in results.items():
        for r in runs:
            print(
                f"live [{name}] {r['size'][0]}x{r['size'][1]}, camera {r['camera_hz']:g} Hz, trainer beside: "
                f"{r['images_per_s']:.1f} images/s for {r['poses_per_s']:.1f} poses/s; frame age p50 "
                f"{r['age_ms_p50']:.0f} ms, p95 {r['age_ms_p95']:.0f} ms; "
                f"render p50 {r['render_ms_p50']:.1f} ms; trainer niceness {r.get('trainer_nice')}"
            )


if __name__ == "__main__":
    sys.exit(main())
