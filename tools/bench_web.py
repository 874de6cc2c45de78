"""Frame age of the web page: from an avatar image's publish stamp to the moment the page draws it
(docs/BENCHMARKS.md, "Live views"). Target: <= 100 ms at 256 x 256.

    python tools/bench_web.py                        # synthetic renderer: 256 x 256 at 30 Hz, 30 s
    python tools/bench_web.py --demo                 # the real pipeline: launch/demo.yaml web:=PORT
    python tools/bench_web.py --size 512 --rate 15 --seconds 60 --screenshot docs/web_operator.png

What runs: a broker, the web node as its own process (``python -m stg_node.nodes web``), and
headless Chromium (tools/headless_chromium.py) on ``/avatar``, which measures each frame's age
itself (the page's own clock, offset to the server's by ping round trips). In the same run, as
baselines on the same images: a bus subscriber in this process (publish stamp -> received: the
bus hop alone) and a Python WebSocket client of the same page stream (publish stamp -> JPEG
received and decoded: everything but the browser). ``--demo`` replaces the synthetic renderer by
``launch/demo.yaml`` (synthetic subject, online training and the real renderer, on this CPU
with everything else the demo runs), with the same measurements.

Prints one JSON line with the medians and 95th percentiles of each, their ratios to the
baselines, the machine's load average and the number of CPUs.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))

from baseline import child_env  # noqa: E402
from headless_chromium import HeadlessChromium  # noqa: E402


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def percentiles(values) -> dict:
    if not values:
        return {"n": 0, "p50_ms": None, "p95_ms": None}
    arr = np.asarray(values, np.float64)
    return {
        "n": len(arr),
        "p50_ms": round(float(np.median(arr)), 1),
        "p95_ms": round(float(np.percentile(arr, 95)), 1),
    }


def avatar_frames(size: int, count: int = 30) -> list[np.ndarray]:
    """A moving, shaded disc: content like a rendered avatar on black (JPEG cost alike)."""
    yy, xx = np.mgrid[:size, :size].astype(np.float32) / size
    frames = []
    for i in range(count):
        cx = 0.5 + 0.15 * np.sin(2 * np.pi * i / count)
        r2 = (xx - cx) ** 2 + (yy - 0.5) ** 2
        shade = np.clip(1.0 - r2 / 0.12, 0, 1)
        image = np.stack([shade * 220, shade * (120 + 80 * yy), shade * (60 + 100 * xx)], axis=-1)
        frames.append(image.astype(np.uint8))
    return frames


class BusAges:
    """Publish stamp -> received, for avatar/image on the bus (the bus hop alone)."""

    def __init__(self, url: str):
        from stg_node.bus import BusConfig, Subscriber

        self.ages: list[float] = []
        self.measuring = False
        self._stop = threading.Event()
        self._sub = Subscriber(BusConfig(url=url), ["avatar/image"], keep_last=True)
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self._sub.recv(timeout=0.1)
            if msg is not None and self.measuring:
                self.ages.append((time.time_ns() - msg.header.stamp_ns) / 1e6)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self._sub.close()


class SocketAges:
    """Publish stamp -> JPEG received and decoded, for a Python client of the page's stream."""

    def __init__(self, port: int):
        self.ages: list[float] = []
        self.measuring = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(port,), daemon=True)
        self._thread.start()

    def _run(self, port: int) -> None:
        import struct

        import cv2
        from websockets.exceptions import ConnectionClosed
        from websockets.sync.client import connect

        with connect(f"ws://127.0.0.1:{port}/ws", max_size=None, open_timeout=30) as ws:
            ws.send(json.dumps({"op": "subscribe", "streams": ["avatar"]}))
            while not self._stop.is_set():
                try:
                    data = ws.recv(timeout=0.2)
                except TimeoutError:
                    continue
                except ConnectionClosed:
                    return
                if isinstance(data, str):
                    continue
                (length,) = struct.unpack_from(">I", data)
                meta = json.loads(data[4 : 4 + length])
                cv2.imdecode(np.frombuffer(data, np.uint8, offset=4 + length), cv2.IMREAD_COLOR)
                if self.measuring:
                    self.ages.append((time.time_ns() - meta["stamp_ns"]) / 1e6)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)


def synthetic_renderer(url: str, size: int, rate: float, stop: threading.Event) -> threading.Thread:
    from stg_node.bus import Bus, RenderedImage

    frames = avatar_frames(size)
    K = np.array([[size, 0, size / 2], [0, size, size / 2], [0, 0, 1]], np.float64)

    def run() -> None:
        with Bus(url, node="renderer", heartbeat_s=1.0) as bus:
            bus.publisher.wait_for_subscribers("avatar/image", 30)
            i, next_t = 0, time.monotonic()
            while not stop.is_set():
                bus.publish(
                    RenderedImage(image=frames[i % len(frames)], K=K, R=np.eye(3), t=np.array([0, 0, 3.0]))
                )
                i += 1
                next_t += 1.0 / rate
                time.sleep(max(0.0, next_t - time.monotonic()))

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def spawn(args: list[str]) -> subprocess.Popen:
    env = child_env(ROOT, STG_THREADS=os.environ.get("STG_THREADS", "1"))
    return subprocess.Popen(
        [sys.executable, *args], cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        start_new_session=True,
    )  # fmt: skip


def stop_process(proc: subprocess.Popen, timeout: float = 60) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def measure(args) -> dict:
    from stg_node.bus import Broker

    work = Path(tempfile.mkdtemp(prefix="stg-bench-web-"))
    url = f"ipc://{work}/bus"
    port = free_port()
    stop = threading.Event()
    with contextlib.ExitStack() as stack:  # closed last-in first-out: browser, clients, nodes, broker
        if args.demo:
            demo = str(ROOT / "launch" / "demo.yaml")
            launch = spawn(
                ["-m", "stg_node.cli.launch", demo, f"out:={work}/demo", f"bus:={url}", f"size:={args.size}",
                 f"frames:={args.frames}", "iters:=100000", f"web:={port}", "--no-color"]
            )  # fmt: skip
            stack.callback(stop_process, launch)
        else:
            stack.enter_context(Broker(url, status_period_s=1.0))
            stack.callback(
                stop_process, spawn(["-m", "stg_node.nodes", "web", "--port", str(port), "--bus", url])
            )
            stack.callback(stop.set)
            synthetic_renderer(url, args.size, args.rate, stop)
        bus_ages = BusAges(url)
        stack.callback(bus_ages.close)
        browser = stack.enter_context(HeadlessChromium(width=args.width, height=args.height, timeout=120))
        deadline = time.monotonic() + args.startup
        while True:  # the page server may still be starting (the demo generates its subject first)
            try:
                with socket.create_connection(("127.0.0.1", port), timeout=1):
                    break
            except OSError:
                if time.monotonic() > deadline:
                    raise RuntimeError(f"the web node did not open port {port} in {args.startup} s") from None
                time.sleep(1.0)
        socket_ages = SocketAges(port)
        stack.callback(socket_ages.close)
        browser.open(f"http://127.0.0.1:{port}/avatar?stats=1")
        browser.wait_for("window.stgStats && window.stgStats.avatar.shown >= 10", timeout=args.startup)
        time.sleep(args.warmup)
        browser.evaluate("window.stgStats.reset()")
        bus_ages.measuring = socket_ages.measuring = True
        time.sleep(args.seconds)
        page = browser.evaluate("window.stgStats.avatar")
        bus_ages.measuring = socket_ages.measuring = False
        if args.screenshot:  # the operator page, once it shows the camera and the nodes
            browser.open(f"http://127.0.0.1:{port}/")
            browser.wait_for(
                "window.stgStats && window.stgStats.status && window.stgStats.avatar.shown >= 5 "
                "&& (window.stgStats.camera.shown >= 5 || !window.stgStats.status.nodes.ingest)",
                timeout=120,
            )
            time.sleep(2.0)  # a few status updates: rates filled in
            Path(args.screenshot).write_bytes(browser.screenshot())
    shutil.rmtree(work, ignore_errors=True)
    page_stats = {
        "n": page["shown"],
        "p50_ms": round(page["age_p50_ms"], 1),
        "p95_ms": round(page["age_p95_ms"], 1),
    }
    socket_stats, bus_stats = percentiles(socket_ages.ages), percentiles(bus_ages.ages)

    def ratio(a, b):
        return round(a / b, 2) if a and b else None

    return {
        "mode": "demo" if args.demo else "synthetic",
        "size": args.size,
        "rate_hz": None if args.demo else args.rate,
        "seconds": args.seconds,
        "page": {**page_stats, "fps": round(page["fps"], 1), "skipped": page["skipped"]},
        "python_websocket_client": socket_stats,
        "bus_subscriber": bus_stats,
        "page_over_websocket_p50": ratio(page_stats["p50_ms"], socket_stats["p50_ms"]),
        "page_over_bus_p50": ratio(page_stats["p50_ms"], bus_stats["p50_ms"]),
        "target_p50_ms": 100,
        "load_avg_1m": round(os.getloadavg()[0], 2),
        "cpus": os.cpu_count(),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--demo", action="store_true", help="the real pipeline (launch/demo.yaml) as the source"
    )
    parser.add_argument("--size", type=int, default=256, help="image side in pixels (default 256)")
    parser.add_argument("--rate", type=float, default=30.0, help="synthetic renderer: images per second")
    parser.add_argument("--frames", type=int, default=60, help="--demo: frames of the synthetic subject")
    parser.add_argument("--seconds", type=float, default=30.0, help="measuring window")
    parser.add_argument("--warmup", type=float, default=5.0, help="seconds before measuring")
    parser.add_argument("--startup", type=float, default=600.0, help="seconds allowed for the first frames")
    parser.add_argument("--width", type=int, default=1280, help="browser window width")
    parser.add_argument("--height", type=int, default=720, help="browser window height")
    parser.add_argument("--screenshot", metavar="PNG", help="at the end, save the operator page (/) as shown")
    args = parser.parse_args(argv)
    print(json.dumps(measure(args)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
