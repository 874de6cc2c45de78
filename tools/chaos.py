#!/usr/bin/env python3
"""Chaos for a running launch: nodes killed in turn, a garbage flood, a subscriber that never reads,
the broker killed; watched from outside by raw pyzmq subscribers, measured against the targets.

    python tools/chaos.py launch/replay_zju.yaml data_root:=runs/zju_subject preset:=fast \\
        [--duration 240] [--every 25] [--kill trainer,renderer,tracker,ingest] \\
        [--scenarios kills,flood,slow,broker] [--json runs/chaos.json] [--work DIR]

One launch (``stg-launch FILE ARGS --no-broker``) on a private ipc bus (``bus:=`` when the file
declares that argument), with a broker this tool runs itself (``stg-broker``) so that the broker
can be killed too; a recording (``record:=``, when declared) runs throughout. Phases:

1. warm-up: every kind node sends heartbeats, avatar/image flows, the trainer has a checkpoint.
2. kills (``--duration`` s): every ``--every`` s the next node of ``--kill`` gets SIGKILL. For each:
   the time until a heartbeat comes from a new pid of that name ("back"); the longest time
   without an avatar/image until the next kill; for the renderer the time until the first image
   of its new process; for the trainer the checkpoint it resumed from (its first iteration after
   the respawn must be the checkpoint's next) and the training time lost (at most one checkpoint
   interval); the recording read back as it is being written (it must stay readable).
3. flood (``--flood-s``): junk on every lane as fast as a raw socket sends it; no node may die,
   the junk must show up as counted drops, and the avatar keeps flowing.
4. slow subscriber (``--slow-s``): a raw SUB on every lane that never reads; no node's resident
   memory may grow (nor the broker's), and the avatar keeps flowing.
5. broker (``--broker-down`` s): the broker gets SIGKILL and comes back; no node may exit, and
   the avatar flows again.
6. SIGINT to stg-launch: it must end, the recording must be complete, and no process it started
   may be left (its pids, found through their STG_LAUNCH_PID, gone within 30 s).

Targets (issue 20): every node back within 10 s, the avatar never gone for more than 6 s, a
killed renderer back within 3 s, the trainer resumed from its checkpoint losing at most one
checkpoint interval, the recording readable, no process left. Exit code 0 when every target is
met, 1 when one is missed, 2 for bad usage. Figures: docs/BENCHMARKS.md ("Chaos").
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import msgpack  # noqa: E402
import zmq  # noqa: E402

from stg_node.bus.config import lane_endpoint  # noqa: E402
from stg_node.launch import read_launch  # noqa: E402
from stg_node.launch.spec import parse_overrides  # noqa: E402
from stg_node.nodes.runtime import ENV_PARENT_PID  # noqa: E402

TARGET_BACK_S = 10.0
TARGET_AVATAR_GAP_S = 6.0
TARGET_RENDERER_BACK_S = 3.0
ORPHAN_WAIT_S = 30.0
LANE_NAMES = ("latest", "reliable", "bulk")


# --- watching from outside ----------------------------------------------------------------------------


class Watcher:
    """Raw pyzmq subscribers (no stg_node decoding: msgpack headers only) on node/status,
    trainer/metrics and avatar/image, recording when each message arrived."""

    def __init__(self, url: str, namespace: str = ""):
        prefix = f"{namespace}/" if namespace else ""
        self.topics = {t: (prefix + t).encode() for t in ("node/status", "trainer/metrics", "avatar/image")}
        self.ctx = zmq.Context()
        self.socks = []
        for lane, topics in (("reliable", ("node/status", "trainer/metrics")), ("latest", ("avatar/image",))):
            sock = self.ctx.socket(zmq.SUB)
            sock.linger = 0
            sock.rcvhwm = 100_000 if lane == "reliable" else 4
            sock.connect(lane_endpoint(url, lane, "out"))
            for topic in topics:
                sock.subscribe(self.topics[topic])
            self.socks.append(sock)
        self.lock = threading.Lock()
        self.status: list[tuple[float, str, int, str, dict]] = []  # (t, node, pid, state, drops)
        self.metrics: list[tuple[float, int, float]] = []  # (t, iteration, it/s)
        self.images: list[tuple[float, str, int]] = []  # (t, src, seq)
        self.sizes: dict[str, float] = {}  # topic -> the largest mean message size the broker reported
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="chaos-watch", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        poller = zmq.Poller()
        for sock in self.socks:
            poller.register(sock, zmq.POLLIN)
        while not self._stop.is_set():
            for sock, _ in poller.poll(100):
                while sock.get(zmq.EVENTS) & zmq.POLLIN:
                    frames = sock.recv_multipart()
                    now = time.monotonic()
                    if len(frames) < 2:
                        continue
                    try:
                        header = msgpack.unpackb(frames[1], raw=False)
                    except Exception:
                        continue
                    if not isinstance(header, dict):
                        continue
                    topic = frames[0]
                    with self.lock:
                        if topic == self.topics["node/status"] and header.get("node") == "broker":
                            rates, rate_bytes = header.get("rates_hz") or {}, header.get("bytes_per_s") or {}
                            for name, hz in rates.items():
                                if hz and name in rate_bytes:
                                    size = rate_bytes[name] / hz
                                    self.sizes[name] = max(self.sizes.get(name, 0.0), size)
                        if topic == self.topics["node/status"]:
                            self.status.append(
                                (now, str(header.get("node")), int(header.get("pid", -1)),
                                 str(header.get("state")), dict(header.get("drops") or {}))
                            )  # fmt: skip
                        elif topic == self.topics["trainer/metrics"]:
                            self.metrics.append(
                                (now, int(header.get("iteration", -1)), float(header.get("it_per_s", 0.0)))
                            )
                        elif topic == self.topics["avatar/image"]:
                            self.images.append((now, str(header.get("src")), int(header.get("seq", -1))))

    # -- questions about what was seen ------------------------------------------------------------------

    def pids(self, running_only: bool = True) -> dict[str, int]:
        """The newest pid each node announced."""
        out: dict[str, int] = {}
        with self.lock:
            for _t, node, pid, state, _d in self.status:
                if not running_only or state in ("running", "degraded"):
                    out[node] = pid
        return out

    def all_pids(self) -> set[int]:
        with self.lock:
            return {pid for _t, node, pid, _s, _d in self.status if node != "broker"}

    def heard_since(self, node: str, t: float, other_than: int | None = None) -> float | None:
        """When ``node`` first sent a running heartbeat after ``t`` (from a pid other than ``other_than``)."""
        with self.lock:
            for when, name, pid, state, _d in self.status:
                if when > t and name == node and state in ("running", "degraded") and pid != other_than:
                    return when
        return None

    def drops(self) -> dict[str, int]:
        """Total drops each node last reported."""
        out: dict[str, int] = {}
        with self.lock:
            for _t, node, _pid, _s, drops in self.status:
                out[node] = sum(int(v) for v in drops.values())
        return out

    def image_times(self, start: float, end: float) -> list[float]:
        with self.lock:
            return [t for t, _src, _seq in self.images if start <= t <= end]

    def longest_gap(self, start: float, end: float) -> float:
        """The longest time in [start, end] without an avatar/image (the edges count as gaps)."""
        with self.lock:
            before = [t for t, _s, _q in self.images if t < start]
        times = ([before[-1]] if before else [start]) + self.image_times(start, end) + [end]
        return max(b - a for a, b in zip(times, times[1:], strict=False))

    def first_image_of_a_new_renderer(self, t: float) -> float | None:
        """The first image after ``t`` from a renderer process that started anew (its seq restarted)."""
        with self.lock:
            last_seq: dict[str, int] = {}
            for when, src, seq in self.images:
                if when > t and seq <= last_seq.get(src, -1):
                    return when
                last_seq[src] = seq
        return None

    def iterations(self, start: float, end: float) -> list[tuple[float, int, float]]:
        with self.lock:
            return [m for m in self.metrics if start <= m[0] <= end]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        for sock in self.socks:
            sock.close()
        self.ctx.term()


# --- the processes -----------------------------------------------------------------------------------


def python(*args: str) -> list[str]:
    return [sys.executable, *args]


def rss_mb(pid: int) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
        state = Path(f"/proc/{pid}/stat").read_text().split(") ", 1)[1][0]
    except (OSError, IndexError):
        return False
    return state != "Z"


def launched_by(launcher_pid: int) -> set[int]:
    """Pids of processes whose environment names ``launcher_pid`` as their launcher (nodes, standby
    copies, commands; what they started inherits it too)."""
    marker = f"{ENV_PARENT_PID}={launcher_pid}".encode()
    found = set()
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            if marker in (entry / "environ").read_bytes().split(b"\0"):
                found.add(int(entry.name))
        except OSError:
            continue
    return found


class Broker:
    """``stg-broker`` as a process of its own, so it can be killed and started again."""

    def __init__(self, url: str, log: Path):
        self.url, self.log = url, log
        self.proc: subprocess.Popen | None = None

    def start(self) -> None:
        with open(self.log, "a") as out:
            self.proc = subprocess.Popen(
                python("-m", "stg_node.cli.broker", "--bus", self.url, "--status-period", "1"),
                cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, start_new_session=True,
            )  # fmt: skip

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


# --- results -----------------------------------------------------------------------------------------


@dataclass
class KillResult:
    node: str
    at_s: float  # since the kills began
    pid: int
    back_s: float | None  # a heartbeat from a new pid
    avatar_gap_s: float  # longest time without avatar/image until the next kill
    image_back_s: float | None = None  # renderer: first image of its new process
    checkpoint_iteration: int | None = None  # trainer: the checkpoint it left
    last_iteration: int | None = None  # trainer: its last metrics before the kill
    resumed_at: int | None = None  # trainer: its first iteration after coming back
    lost_s: float | None = None  # trainer: training time lost (iterations past the checkpoint)
    recording_messages: int | None = None  # messages readable from the recording right after
    problems: list[str] = field(default_factory=list)


def checkpoint_iteration(path: Path) -> int | None:
    """The iteration of a trainer checkpoint file (or a copy of one)."""
    if not path.is_file():
        return None
    from stg_node.avatar.snapshot import read_snapshot_file

    try:
        return int(read_snapshot_file(path).iteration)
    except Exception:
        try:  # the stand-in avatar of the tests writes numpy files
            import numpy as np

            return int(np.load(path)["iteration"])
        except Exception:
            return None


def keep_copy(path: Path | None, to: Path) -> Path | None:
    """A copy of the checkpoint the killed trainer left, taken at once: its successor, back within
    seconds, writes its own there one interval later."""
    if path is None or not path.is_file():
        return None
    to.write_bytes(path.read_bytes())
    return to


def recording_count(path: Path | None) -> tuple[int | None, str]:
    """Messages readable from a recording (while it is written: up to its last whole chunk)."""
    if path is None or not path.exists():
        return None, ""
    from stg_node.bus.recording import BagReader

    try:
        reader = BagReader(path)
        truncated = any(f.truncated for f in reader.files)
        return reader.message_count, "in progress" if truncated else "complete"
    except Exception as exc:
        return None, f"unreadable: {exc}"


# --- the run -------------------------------------------------------------------------------------------


class Chaos:
    def __init__(self, args, work: Path):
        self.args = args
        self.work = work
        overrides = parse_overrides(args.launch_args)
        declared = {a.name for a in read_launch(args.launch_file, overrides).args}
        self.overrides = {**overrides, **self._own_args(declared, overrides)}
        self.spec = read_launch(args.launch_file, self.overrides)
        self.url = self.spec.bus.url
        self.kind_nodes = [n for n in self.spec.nodes if n.entry.kind is not None]
        self.trainer = next((n for n in self.kind_nodes if n.entry.kind == "trainer"), None)
        self.recording = Path(self.overrides["record"]) if self.overrides.get("record") else None
        self.results: dict = {"kills": [], "problems": []}
        self.launcher: subprocess.Popen | None = None
        self.broker = Broker(self.url, work / "broker.log")
        self.watcher: Watcher | None = None
        self.seen_pids: set[int] = set()

    def _own_args(self, declared: set[str], overrides: dict) -> dict:
        """A private bus and a recording, where the launch file lets us choose them."""
        own = {}
        if "bus" in declared and "bus" not in overrides:
            own["bus"] = f"ipc://{self.work}/bus"
        if "record" in declared and "record" not in overrides and "record" in self.args.scenarios_recording:
            own["record"] = str(self.work / "chaos.mcap")
        return own

    # -- life cycle ---------------------------------------------------------------------------------

    def start(self) -> None:
        if self.trainer is not None:
            import stg_node.avatar.snapshot  # noqa: F401  (read a checkpoint at once when one is killed)
        self.broker.start()
        args = [f"{k}:={v}" for k, v in self.overrides.items()]
        self.launch_log = open(self.work / "launch.log", "w")  # noqa: SIM115
        command = python("-m", "stg_node.cli.launch", str(self.args.launch_file), *args)
        self.launcher = subprocess.Popen(
            [*command, "--no-broker", "--no-color"],
            cwd=ROOT, stdout=self.launch_log, stderr=subprocess.STDOUT, start_new_session=True,
        )  # fmt: skip
        self.watcher = Watcher(self.url, self.spec.bus.namespace)

    def note_pids(self) -> None:
        if self.launcher is not None:
            self.seen_pids |= launched_by(self.launcher.pid)
        if self.watcher is not None:
            self.seen_pids |= self.watcher.all_pids()

    def warm_up(self) -> float:
        names = {n.name for n in self.kind_nodes}
        renders = any(n.entry.kind == "renderer" for n in self.kind_nodes)
        checkpoint = self._checkpoint_path()
        start = time.monotonic()
        deadline = start + self.args.warmup_timeout
        while time.monotonic() < deadline:
            if self.launcher.poll() is not None:
                raise SystemExit(
                    f"chaos: stg-launch ended during the warm-up; see {self.work / 'launch.log'}"
                )
            up = names <= set(self.watcher.pids())
            images = not renders or self.watcher.image_times(time.monotonic() - 5, time.monotonic())
            ready = checkpoint is None or checkpoint.is_file()
            if up and images and ready:
                self.note_pids()
                return time.monotonic() - start
            time.sleep(0.5)
        missing = names - set(self.watcher.pids())
        raise SystemExit(
            f"chaos: not warmed up within {self.args.warmup_timeout:g} s (nodes missing: {sorted(missing)}, "
            f"checkpoint {checkpoint}); see {self.work / 'launch.log'}"
        )

    def _checkpoint_path(self) -> Path | None:
        if self.trainer is None or not self.trainer.params.checkpoint_dir:
            return None
        from stg_node.nodes.trainer import CHECKPOINT_NAME

        return Path(self.trainer.params.checkpoint_dir) / CHECKPOINT_NAME

    # -- phase: kills -------------------------------------------------------------------------------

    def kills(self) -> None:
        order = [n for n in self.args.kill if n in {k.name for k in self.kind_nodes}]
        if not order:
            return
        begin = time.monotonic()
        count = int(self.args.duration // self.args.every)
        for k in range(count):
            at = begin + k * self.args.every + self.args.every / 2  # the first kill after half a period
            self._sleep_until(at)
            name = order[k % len(order)]
            self.results["kills"].append(
                self._kill(name, begin, begin + (k + 1) * self.args.every + self.args.every / 2)
            )

    def _sleep_until(self, t: float) -> None:
        while (left := t - time.monotonic()) > 0:
            self.note_pids()
            time.sleep(min(left, 1.0))

    def _kill(self, name: str, begin: float, next_kill: float) -> dict:
        pid = self.watcher.pids().get(name)
        if pid is None or not alive(pid):
            return asdict(KillResult(name, time.monotonic() - begin, -1, None, 0.0, problems=["not running"]))
        metrics_before = self.watcher.iterations(0, time.monotonic())
        killed_at = time.monotonic()
        os.kill(pid, signal.SIGKILL)
        result = KillResult(name, killed_at - begin, pid, None, 0.0)
        if self.trainer is not None and name == self.trainer.name:
            left = keep_copy(self._checkpoint_path(), self.work / "checkpoint-at-kill")
            result.checkpoint_iteration = None if left is None else checkpoint_iteration(left)
            result.last_iteration = metrics_before[-1][1] if metrics_before else None
        deadline = killed_at + max(30.0, self.args.every)
        while (
            time.monotonic() < deadline and self.watcher.heard_since(name, killed_at, other_than=pid) is None
        ):
            time.sleep(0.1)
        # from the watcher's own arrival times, so the figure does not depend on when we look
        back = self.watcher.heard_since(name, killed_at, other_than=pid)
        result.back_s = None if back is None else back - killed_at
        count, how = recording_count(self.recording)  # (scanning a growing file takes a while)
        result.recording_messages = count
        if self.recording is not None and count is None:
            result.problems.append(f"recording {how or 'missing'}")
        self._sleep_until(min(next_kill - 0.5, killed_at + self.args.every - 0.5))
        end = min(time.monotonic(), next_kill)
        result.avatar_gap_s = self.watcher.longest_gap(killed_at, end)
        if any(n.entry.kind == "renderer" and n.name == name for n in self.kind_nodes):
            first = self.watcher.first_image_of_a_new_renderer(killed_at)
            result.image_back_s = None if first is None else first - killed_at
        if result.checkpoint_iteration is not None:
            after = [m for m in self.watcher.iterations(killed_at, end)]
            if after:
                result.resumed_at = after[0][1]
                rates = [m[2] for m in metrics_before[-50:] if m[2] > 0]
                lost = (result.last_iteration or 0) - result.checkpoint_iteration
                result.lost_s = lost / statistics.median(rates) if rates else None
        self._judge(result)
        return asdict(result)

    def _judge(self, r: KillResult) -> None:
        if r.back_s is None:
            r.problems.append("never came back")
        elif r.back_s > TARGET_BACK_S:
            r.problems.append(f"back after {r.back_s:.1f} s > {TARGET_BACK_S:g} s")
        if r.avatar_gap_s > TARGET_AVATAR_GAP_S:
            r.problems.append(f"avatar gone for {r.avatar_gap_s:.1f} s > {TARGET_AVATAR_GAP_S:g} s")
        if r.image_back_s is not None and r.image_back_s > TARGET_RENDERER_BACK_S:
            r.problems.append(
                f"renderer's first image after {r.image_back_s:.1f} s > {TARGET_RENDERER_BACK_S:g} s"
            )
        if r.checkpoint_iteration is not None:
            if r.resumed_at is None:
                r.problems.append("no iteration after the respawn")
            elif r.resumed_at != r.checkpoint_iteration + 1:
                r.problems.append(
                    f"resumed at {r.resumed_at}, not after the checkpoint's {r.checkpoint_iteration}"
                )
            interval = float(self.trainer.params.checkpoint_every_s)
            if r.lost_s is not None and interval and r.lost_s > interval * 1.1:
                r.problems.append(
                    f"lost {r.lost_s:.0f} s of training > one checkpoint interval ({interval:g} s)"
                )

    # -- phase: flood -------------------------------------------------------------------------------

    def flood(self) -> None:
        pids_before = self.watcher.pids()
        drops_before = self.watcher.drops()
        stop = threading.Event()
        sent = [0]

        def junk():
            ctx = zmq.Context()
            socks = []
            for lane in LANE_NAMES:
                sock = ctx.socket(zmq.PUB)
                sock.linger = 0
                sock.connect(lane_endpoint(self.url, lane, "in"))
                socks.append(sock)
            topics = {
                "latest": [b"camera/frame", b"avatar/image"],
                "reliable": [b"body/pose", b"avatar/view"],
                "bulk": [b"avatar/snapshot"],
            }
            lie = {"name": "image", "dtype": "uint8", "shape": [4000, 4000, 3]}  # 48 MB promised, 4 B sent
            header = msgpack.packb(
                {
                    "type": "Frame",
                    "v": 1,
                    "seq": 0,
                    "stamp_ns": 1,
                    "src": "chaos",
                    "index": 0,
                    "arrays": [lie],
                }
            )
            bodies = (
                [b"\xc1\xff not msgpack"],
                [msgpack.packb({"type": "NodeStatus", "v": 1})],
                [header, b"tiny"],
                [msgpack.packb([1, 2, 3]), b"", b""],
                [],
            )
            try:
                while not stop.is_set():
                    for sock, lane in zip(socks, LANE_NAMES, strict=True):
                        for topic in topics[lane]:
                            for body in bodies:
                                try:
                                    sock.send_multipart([topic, *body], zmq.NOBLOCK)
                                    sent[0] += 1
                                except zmq.Again:
                                    pass
            finally:
                for sock in socks:
                    sock.close()
                ctx.term()

        start = time.monotonic()
        thread = threading.Thread(target=junk, daemon=True)
        thread.start()
        self._sleep_until(start + self.args.flood_s)
        stop.set()
        thread.join(10)
        end = time.monotonic()
        self._sleep_until(end + 3)  # the last heartbeats with the counts
        pids_after = self.watcher.pids()
        drops_after = self.watcher.drops()
        died = sorted(n for n, p in pids_before.items() if pids_after.get(n) != p and n != "broker")
        counted = {n: drops_after.get(n, 0) - drops_before.get(n, 0) for n in pids_before if n != "broker"}
        result = {
            "seconds": end - start,
            "junk_sent": sent[0],
            "junk_per_s": sent[0] / max(end - start, 1e-9),
            "drops_counted": counted,
            "nodes_restarted": died,
            "avatar_gap_s": self.watcher.longest_gap(start, end),
            "problems": [],
        }
        if died:
            result["problems"].append(f"nodes restarted: {died}")
        if not any(v > 0 for v in counted.values()):
            result["problems"].append("no drop counted")
        if result["avatar_gap_s"] > TARGET_AVATAR_GAP_S:
            result["problems"].append(f"avatar gone for {result['avatar_gap_s']:.1f} s")
        self.results["flood"] = result

    # -- phase: a subscriber that never reads ----------------------------------------------------------

    def _sample_memory(self, pids: dict[str, int], seconds: float) -> dict[str, float]:
        """Each process's resident-memory growth over ``seconds`` (median of the last quarter of
        the samples minus that of the first: noise averages out), MB."""
        samples: dict[str, list[float]] = {n: [] for n in pids}
        start = time.monotonic()
        while time.monotonic() < start + seconds:
            for name, pid in pids.items():
                mb = rss_mb(pid)
                if mb == mb:
                    samples[name].append(mb)
            self.note_pids()
            time.sleep(1.0)
        growth = {}
        for name, mbs in samples.items():
            if len(mbs) >= 2:
                quarter = max(1, len(mbs) // 4)
                growth[name] = statistics.median(mbs[-quarter:]) - statistics.median(mbs[:quarter])
        return growth

    def slow(self) -> None:
        """A subscriber on every lane that never reads, against a same-length window without it
        just before: what it makes a process grow is the difference (a trainer also grows on its
        own, densifying)."""
        pids = dict(self.watcher.pids())
        if self.broker.proc is not None:
            pids["broker"] = self.broker.proc.pid
        baseline = self._sample_memory(pids, self.args.slow_s)
        ctx = zmq.Context()
        socks = []
        for lane in LANE_NAMES:
            sock = ctx.socket(zmq.SUB)
            sock.linger = 0
            sock.connect(lane_endpoint(self.url, lane, "out"))
            sock.subscribe(b"")
            socks.append(sock)
        start = time.monotonic()
        try:
            stalled = self._sample_memory(pids, self.args.slow_s)
        finally:
            for sock in socks:
                sock.close()
            ctx.term()
        end = time.monotonic()
        memory = {
            name: {
                "baseline_growth_mb": baseline.get(name, float("nan")),
                "stalled_growth_mb": stalled[name],
                "attributable_mb": stalled[name] - baseline.get(name, 0.0),
            }
            for name in stalled
        }
        # A node must not grow for it; the broker may queue for the stalled subscriber what its
        # lanes' high-water marks allow (that is what they are for; plus a quarter for the
        # allocator's overhead per message), and no more.
        bound = self.queue_bound_mb()
        result = {
            "seconds": end - start,
            "memory": memory,
            "broker_queue_bound_mb": bound,
            "avatar_gap_s": self.watcher.longest_gap(start, end),
            "problems": [],
        }
        allowed = {n: self.args.max_growth_mb + (1.25 * bound if n == "broker" else 0.0) for n in memory}
        grown = {
            n: round(m["attributable_mb"], 1) for n, m in memory.items() if m["attributable_mb"] > allowed[n]
        }
        if grown:
            result["problems"].append(f"memory grew for the stalled subscriber (MB): {grown}")
        if result["avatar_gap_s"] > TARGET_AVATAR_GAP_S:
            result["problems"].append(f"avatar gone for {result['avatar_gap_s']:.1f} s")
        self.results["slow_subscriber"] = result

    def queue_bound_mb(self) -> float:
        """What the broker may hold for one subscriber that never reads: per lane, its high-water
        mark times the largest message seen on it (from the broker's own reports), in MB."""
        from stg_node.bus.config import BusConfig

        config = BusConfig(url=self.url, lanes=dict(self.spec.bus.lanes))
        largest: dict[str, float] = {}
        for topic, size in self.watcher.sizes.items():
            lane = config.lane_of(topic)
            largest[lane.name] = max(largest.get(lane.name, 0.0), size)
        from stg_node.bus.topics import LANES

        return sum(LANES[name].hwm * size for name, size in largest.items()) / 1e6

    # -- phase: the broker killed ----------------------------------------------------------------------

    def broker_down(self) -> None:
        pids_before = self.watcher.pids()
        killed_at = time.monotonic()
        self.broker.kill()
        self._sleep_until(killed_at + self.args.broker_down)
        restarted_at = time.monotonic()
        self.broker.start()
        deadline = restarted_at + 60
        image = heard = None
        while time.monotonic() < deadline and (image is None or heard is None):
            images = self.watcher.image_times(restarted_at, time.monotonic())
            image = images[0] if images else None
            if all(self.watcher.heard_since(n, restarted_at) for n in pids_before if n != "broker"):
                heard = time.monotonic()
            time.sleep(0.2)
        self._sleep_until(time.monotonic() + 3)
        pids_after = self.watcher.pids()
        exited = sorted(
            n for n, p in pids_before.items() if n != "broker" and (pids_after.get(n) != p or not alive(p))
        )
        result = {
            "down_s": restarted_at - killed_at,
            "avatar_back_s": None if image is None else image - restarted_at,
            "nodes_heard_s": None if heard is None else heard - restarted_at,
            "nodes_exited": exited,
            "problems": [],
        }
        if exited:
            result["problems"].append(f"nodes exited: {exited}")
        if image is None:
            result["problems"].append("the avatar did not come back")
        if heard is None:
            result["problems"].append("not every node was heard again")
        self.results["broker"] = result

    # -- the end ----------------------------------------------------------------------------------------

    def cold_starts(self) -> dict[str, float]:
        """Each node's first start to ready, from the launch's log: the same-run baseline of a
        respawn (what a start from nothing costs on this machine now)."""
        import re

        found: dict[str, float] = {}
        for line in (self.work / "launch.log").read_text(errors="replace").splitlines():
            m = re.search(r"stg_node\.launch: (\S+) is ready \(([\d.]+) s\)", line)
            if m and m.group(1) not in found:
                found[m.group(1)] = float(m.group(2))
        return found

    def stop(self) -> None:
        self.note_pids()
        if self.launcher is not None and self.launcher.poll() is None:
            self.launcher.send_signal(signal.SIGINT)
            try:
                self.launcher.wait(180)
            except subprocess.TimeoutExpired:
                self.results["problems"].append("stg-launch did not end within 180 s of SIGINT")
                self.launcher.kill()
                self.launcher.wait()
        deadline = time.monotonic() + ORPHAN_WAIT_S
        while time.monotonic() < deadline and any(alive(p) for p in self.seen_pids):
            time.sleep(0.2)
        left = sorted(p for p in self.seen_pids if alive(p))
        self.results["launch_exit_code"] = None if self.launcher is None else self.launcher.returncode
        self.results["processes_seen"] = len(self.seen_pids)
        self.results["orphans"] = left
        if left:
            self.results["problems"].append(f"{len(left)} process(es) left after SIGINT: {left}")
            for pid in left:
                try:
                    os.kill(pid, signal.SIGKILL)
                except OSError:
                    pass
        if self.watcher is not None:
            self.watcher.close()
        self.broker.stop()
        count, how = recording_count(self.recording)
        if self.recording is not None:
            self.results["recording"] = {"messages": count, "state": how}
            if how != "complete":
                self.results["problems"].append(f"recording {how or 'missing'} after the launch ended")
        if hasattr(self, "launch_log"):
            self.launch_log.close()
            self.results["cold_start_s"] = self.cold_starts()


def report(results: dict) -> list[str]:
    lines = []
    kills = results.get("kills", [])
    if kills:
        head = f"{'kill':>6} {'node':10} {'back s':>7} {'image s':>7} {'gap s':>6}"
        lines.append(head + "  resume / recording / problems")
        for k in kills:
            extra = []
            if k["checkpoint_iteration"] is not None:
                lost = f", lost {k['lost_s']:.0f} s" if k["lost_s"] is not None else ""
                extra.append(f"ckpt {k['checkpoint_iteration']} -> {k['resumed_at']}{lost}")
            if k["recording_messages"] is not None:
                extra.append(f"rec {k['recording_messages']} msgs")
            extra += k["problems"]
            back = "-" if k["back_s"] is None else f"{k['back_s']:.1f}"
            image = "" if k["image_back_s"] is None else f"{k['image_back_s']:.1f}"
            row = f"{k['at_s']:6.0f} {k['node']:10} {back:>7} {image:>7} {k['avatar_gap_s']:6.1f}"
            lines.append(f"{row}  {'; '.join(extra)}")
        cold = results.get("cold_start_s", {})
        if cold:
            lines.append(
                "cold starts (first start to ready, same run): "
                + ", ".join(f"{n} {s:.1f} s" for n, s in cold.items())
            )
        backs = [k["back_s"] for k in kills if k["back_s"] is not None]
        gaps = [k["avatar_gap_s"] for k in kills]
        lines.append(
            f"kills: {len(kills)}, all back: {len(backs) == len(kills)}, "
            f"slowest back {max(backs, default=0):.1f} s (target {TARGET_BACK_S:g}), "
            f"longest avatar gap {max(gaps, default=0):.1f} s (target {TARGET_AVATAR_GAP_S:g})"
        )
    for name in ("flood", "slow_subscriber", "broker"):
        if name in results:
            shown = {k: v for k, v in results[name].items() if k != "memory"}
            lines.append(f"{name}: {json.dumps(shown, default=str)}")
            if name == "slow_subscriber":
                for node, m in results[name]["memory"].items():
                    lines.append(
                        f"    {node:10} {m['baseline_growth_mb']:+7.1f} MB without it, "
                        f"{m['stalled_growth_mb']:+7.1f} MB with it: {m['attributable_mb']:+7.1f} MB"
                    )
    lines.append(
        f"stg-launch exit {results.get('launch_exit_code')}, "
        f"{results.get('processes_seen', 0)} processes seen, "
        f"left after SIGINT: {len(results.get('orphans', []))}; recording: {results.get('recording')}"
    )
    return lines


def all_problems(results: dict) -> list[str]:
    found = list(results.get("problems", []))
    for k in results.get("kills", []):
        found += [f"{k['node']} at {k['at_s']:.0f} s: {p}" for p in k["problems"]]
    for name in ("flood", "slow_subscriber", "broker"):
        found += [f"{name}: {p}" for p in results.get(name, {}).get("problems", [])]
    return found


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("launch_file", help="the launch file")
    parser.add_argument("launch_args", nargs="*", metavar="NAME:=VALUE", help="its arguments")
    parser.add_argument("--duration", type=float, default=240.0, help="seconds of kills (default 240)")
    parser.add_argument("--every", type=float, default=25.0, help="seconds between kills (default 25)")
    parser.add_argument("--kill", default="trainer,renderer,tracker,ingest", help="nodes to kill, in turn")
    parser.add_argument(
        "--scenarios", default="kills,flood,slow,broker", help="which phases: kills, flood, slow, broker"
    )
    parser.add_argument("--no-record", action="store_true", help="do not record (record:= is set otherwise)")
    parser.add_argument("--flood-s", type=float, default=20.0, help="seconds of garbage (default 20)")
    parser.add_argument("--slow-s", type=float, default=60.0, help="seconds of the never-reading subscriber")
    parser.add_argument("--max-growth-mb", type=float, default=20.0, help="memory growth allowed then (MB)")
    parser.add_argument("--broker-down", type=float, default=5.0, help="seconds the broker stays dead")
    parser.add_argument("--warmup-timeout", type=float, default=900.0, help="seconds to wait for the launch")
    parser.add_argument("--work", type=Path, help="folder for logs, bus, recording (default: a temp folder)")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args(argv)
    args.kill = [n.strip() for n in args.kill.split(",") if n.strip()]
    scenarios = {s.strip() for s in args.scenarios.split(",") if s.strip()}
    unknown = scenarios - {"kills", "flood", "slow", "broker"}
    if unknown or args.every <= 0 or args.duration < 0:
        parser.error(
            f"unknown scenarios {sorted(unknown)}" if unknown else "--every must be > 0, --duration >= 0"
        )
    args.scenarios_recording = set() if args.no_record else {"record"}
    os.environ.setdefault("STG_THREADS", "1")
    work = args.work or Path(tempfile.mkdtemp(prefix="stgchaos-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        chaos = Chaos(args, work)
    except Exception as exc:  # a bad launch file or argument: the launcher's own one-line error
        print(f"chaos: {exc}", file=sys.stderr)
        return 2
    results = chaos.results
    load = os.getloadavg()[0]
    results.update(
        machine=f"{platform.node()} {platform.machine()} {os.cpu_count()} cpus, load {load:.1f}",
        launch=str(args.launch_file),
        args=chaos.overrides,
        work=str(work),
    )
    interrupted = False
    try:
        chaos.start()
        results["warmup_s"] = chaos.warm_up()
        print(f"chaos: warmed up in {results['warmup_s']:.0f} s; work folder {work}", flush=True)
        if "kills" in scenarios:
            chaos.kills()
        if "flood" in scenarios:
            chaos.flood()
        if "slow" in scenarios:
            chaos.slow()
        if "broker" in scenarios:
            chaos.broker_down()
    except KeyboardInterrupt:
        interrupted = True
        results["problems"].append("interrupted")
    finally:
        chaos.stop()
    results["load_after"] = os.getloadavg()[0]
    for line in report(results):
        print(line)
    problems = all_problems(results)
    results["targets_met"] = not problems
    print("targets met" if not problems else "targets missed:\n  " + "\n  ".join(problems))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=2, default=str) + "\n")
    if interrupted:
        return 130
    return 0 if not problems else 1


if __name__ == "__main__":
    sys.exit(main())
