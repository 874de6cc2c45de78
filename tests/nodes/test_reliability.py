"""The running system under abuse (fake avatar): kill -9 nodes mid-run, a subscriber that never reads,
a publisher of garbage, and Ctrl-C on the launch. Watched from outside, over the bus.

- every killed node is respawned (a heartbeat with a new pid), the renderer keeps publishing
  while the others are down, and the trainer resumes from its checkpoint (its iterations go on
  from the checkpoint's, not from 1);
- a subscriber that never reads stalls nobody (iterations and images keep coming);
- garbage on every lane crashes nobody (same pids after it) and shows up as counted drops;
- SIGINT on the launch ends it with exit 0 and leaves none of its processes alive.
"""

from __future__ import annotations

import os
import signal
import threading
import time

import msgpack
import numpy as np
import pytest
import zmq
from fixtures.datasets import write_zju_original
from nodehelpers import describe_pids, ignore_sigint, launch_file, pid_alive, spawn, wait_until

from stg_node.bus import BusConfig, Subscriber, lane_endpoint
from stg_node.bus.messages import NodeStatus, RenderedImage, TrainerMetrics

FAKE = "tests.nodes.fake_avatar"
NODES = ("ingest", "tracker", "trainer", "renderer")


class Watcher:
    """Collects heartbeats, metrics and image arrivals in a thread."""

    def __init__(self, url: str):
        self.sub = Subscriber(BusConfig(url=url), ["node/status", "trainer/metrics", "avatar/image"])
        self.lock = threading.Lock()
        self.pids: dict[str, int] = {}
        self.status: dict[str, NodeStatus] = {}
        self.heard: dict[str, float] = {}  # node -> when its last heartbeat came
        self.iterations: list[tuple[float, int]] = []
        self.images: list[tuple[float, int]] = []  # (time, snapshot version)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def run(self) -> None:
        while not self.stop.is_set():
            msg = self.sub.recv(timeout=0.1)
            now = time.monotonic()
            with self.lock:
                if isinstance(msg, NodeStatus) and msg.state != "stopping":
                    self.pids[msg.node] = msg.pid
                    self.status[msg.node] = msg
                    self.heard[msg.node] = now
                elif isinstance(msg, TrainerMetrics):
                    self.iterations.append((now, msg.iteration))
                elif isinstance(msg, RenderedImage):
                    self.images.append((now, msg.snapshot_version))

    def heard_since(self, node: str, t: float) -> bool:
        with self.lock:
            return self.heard.get(node, 0.0) > t

    def images_since(self, t: float) -> int:
        with self.lock:
            return sum(1 for when, _ in self.images if when > t)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(2)
        self.sub.close()


def garbage(url: str) -> None:
    """Junk on every lane and standard topic: bad frame counts, bad msgpack, wrong types, lies about sizes."""
    ctx = zmq.Context()
    socks = []
    try:
        for lane in ("latest", "reliable", "bulk"):
            sock = ctx.socket(zmq.XPUB)  # an XPUB sees the subscriptions reach it: no guessing
            sock.linger = 0
            sock.connect(lane_endpoint(url, lane, "in"))
            socks.append(sock)
        for sock in socks:  # the broker forwards its subscribers' subscriptions (or its own)
            assert sock.poll(30_000), "no subscription reached the garbage publisher"
            sock.recv()
        header = {
            "type": "Frame",
            "v": 1,
            "seq": 0,
            "stamp_ns": 1,
            "src": "evil",
            "index": 0,
            "arrays": [{"name": "image", "dtype": "uint8", "shape": [4000, 4000, 3]}],
        }
        for _ in range(20):
            for sock, topics in zip(
                socks,
                (["camera/frame", "avatar/image"], ["body/pose", "avatar/view"], ["avatar/snapshot"]),
                strict=True,
            ):
                for topic in topics:
                    sock.send_multipart([topic.encode()])
                    sock.send_multipart([topic.encode(), b"\xc1\xff not msgpack"])
                    sock.send_multipart([topic.encode(), msgpack.packb({"type": "NodeStatus", "v": 1})])
                    sock.send_multipart([topic.encode(), msgpack.packb(header), b"tiny"])
                    sock.send_multipart([topic.encode(), msgpack.packb([1, 2, 3]), b"", b""])
            time.sleep(0.02)
    finally:
        for sock in socks:
            sock.close()
        ctx.term()


def write_launch(tmp_path) -> tuple[str, object]:
    data = tmp_path / "subject"
    write_zju_original(data, num_frames=6, num_cams=1)
    path = launch_file(
        tmp_path,
        # respawn_delay 1 s for the nodes the renderer must serve through: a window for its images
        f"""
            env: {{STG_THREADS: "1"}}
            nodes:
              - name: tracker
                kind: tracker
                params: {{path: {data}}}
                respawn: true
                respawn_delay: 1.0
              - name: trainer
                kind: trainer
                params: {{avatar: {FAKE}, preset: slow, snapshot_every_s: 0.5, checkpoint_every_s: 0.5,
                          checkpoint_dir: {tmp_path}/ckpt}}
                respawn: true
                respawn_delay: 1.0
              - name: renderer
                kind: renderer
                params: {{avatar: {FAKE}, size: 48, idle_rate_hz: 10, max_rate_hz: 20}}
                respawn: true
                respawn_delay: 0.2
              - name: ingest
                kind: ingest
                params: {{path: {data}, size: 48, rate_hz: 20, loop: true}}
                after: [tracker, trainer]
                respawn: true
                respawn_delay: 1.0
        """,
    )
    return f"ipc://{tmp_path}/bus", path


def run_scenario(tmp_path, kill: tuple[str, ...]) -> None:
    url, path = write_launch(tmp_path)
    launcher = spawn(["-m", "stg_node.cli.launch", str(path), "--no-color"], preexec_fn=ignore_sigint)
    output: list[str] = []
    reader = threading.Thread(target=lambda: output.extend(iter(launcher.stdout.readline, "")), daemon=True)
    reader.start()
    watcher = Watcher(url)
    # A subscriber that connects to everything and never reads.
    ctx = zmq.Context()
    lazy = []
    for lane in ("latest", "reliable", "bulk"):
        sock = ctx.socket(zmq.SUB)
        sock.linger = 0
        sock.connect(lane_endpoint(url, lane, "out"))
        sock.subscribe(b"")
        lazy.append(sock)
    seen_pids: set[int] = set()
    try:
        assert wait_until(lambda: set(NODES) <= set(watcher.pids) and watcher.images_since(0) > 5, 120), (
            "".join(output)
        )
        checkpoint = tmp_path / "ckpt" / "trainer.ckpt"
        assert wait_until(checkpoint.is_file, 60)
        seen_pids |= set(watcher.pids.values())

        for name in kill:
            old_pid = watcher.pids[name]
            if name == "trainer":
                checkpointed = int(np.load(checkpoint)["iteration"])  # the fake avatar's file
            killed_at = time.monotonic()
            os.kill(old_pid, signal.SIGKILL)
            if name != "renderer":  # the renderer serves on while the node is down
                assert wait_until(lambda t=killed_at: watcher.images_since(t) >= 3, 60)
                assert watcher.pids[name] == old_pid, f"{name} came back before 3 images were served"
            assert wait_until(lambda n=name, p=old_pid: watcher.pids.get(n, p) != p, 60), (
                f"{name} not respawned"
            )
            back_at = time.monotonic()
            seen_pids.add(watcher.pids[name])
            assert wait_until(lambda t=back_at: watcher.images_since(t) > 3, 60), (
                f"no images after {name} came back"
            )
            if name == "trainer":
                assert wait_until(lambda t=back_at: any(w > t for w, _ in watcher.iterations), 30)
                with watcher.lock:
                    after = [it for w, it in watcher.iterations if w > back_at]
                assert after[0] > checkpointed, (after[:3], checkpointed)  # resumed, not from 1

        pids_before = dict(watcher.pids)
        dropped_before = sum(watcher.status["tracker"].drops.values())
        garbage(url)
        # the junk is counted (the tracker's heartbeat says so) ...
        assert wait_until(lambda: sum(watcher.status["tracker"].drops.values()) > dropped_before, 60)
        t = time.monotonic()
        # ... and every node beats on after it, with the pid it had: nobody crashed
        assert wait_until(lambda: all(watcher.heard_since(n, t) for n in NODES), 60)
        assert watcher.pids == pids_before
        with watcher.lock:
            iteration = watcher.iterations[-1][1]
        assert wait_until(
            lambda: watcher.images_since(t) > 3 and watcher.iterations[-1][1] > iteration + 5, 60
        )
    finally:
        launcher.send_signal(signal.SIGINT)
        try:
            launcher.wait(timeout=60)
        finally:
            watcher.close()
            for sock in lazy:
                sock.close()
            ctx.term()
            reader.join(5)
    log = "".join(output)
    assert launcher.returncode == 0, log[-3000:]
    for node in NODES:
        assert f"[{node}] " in log
    assert wait_until(lambda: not any(pid_alive(p) for p in seen_pids), 30), describe_pids(seen_pids)


def test_kill_the_trainer_garbage_a_lazy_subscriber_and_ctrl_c(tmp_path):
    run_scenario(tmp_path, kill=("trainer",))


@pytest.mark.slow
def test_kill_each_node_in_turn(tmp_path):
    run_scenario(tmp_path, kill=NODES)
