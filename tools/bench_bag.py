#!/usr/bin/env python3
"""Recording speed (stg-bag): MCAP writing and live recording against same-run baselines.

Three measurements, all on 1080p RGB camera frames (a Frame message of 6.2 MB):

1. writer:  BagWriter.write_frames of the encoded frames (compression none, lz4, zstd) into a
            file, against the baseline of writing the same bytes with plain file writes
            (header, then each buffer) to the same folder. Alternating repeats; MB/s =
            payload bytes / time until the file is closed.
2. live:    a broker process and a publisher process sending a burst of frames on a reliable
            custom topic as fast as the bus takes them; this process records them with the
            Recorder (the library stg-bag record runs). MB/s = payload bytes / (file closed -
            first frame received). Baseline, alternating with it in the same run: the same
            burst received by a plain Subscriber that keeps nothing (the bus's own ceiling).
3. camera:  the publisher sends camera/frame (keep-last lane) at 30 fps for --seconds; the
            recorder must keep every frame: sent, recorded and drops are reported. With
            --witness a plain subscriber process receives the stream too: losses it shares
            happened upstream of the broker (a saturated machine), not in the recorder.

    python tools/bench_bag.py [--frames 60] [--repeats 5] [--seconds 10] [--dir DIR] [--json out.json]

Quick smoke run: python tools/bench_bag.py --frames 8 --repeats 1 --seconds 2
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import platform
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

H, W = 1080, 1920
BURST_TOPIC = "bench/frame"  # a custom topic: the reliable lane, lossless
CAMERA_TOPIC = "camera/frame"  # the keep-last lane, as a real camera


def _frame(seed: int):
    from stg_node.bus import Frame

    rng = np.random.default_rng(seed)
    return Frame(
        index=seed,
        image=rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
        K=np.array([[1000.0, 0, W / 2], [0, 1000.0, H / 2], [0, 0, 1]]),
        R=np.eye(3),
        t=np.zeros(3),
    )


def _encoded(count: int, distinct: int = 4) -> list[list]:
    from stg_node.bus import encode

    frames = [_frame(i) for i in range(distinct)]
    return [
        encode(frames[i % distinct], topic=BURST_TOPIC, seq=i, src="bench", stamp_ns=time.time_ns())
        for i in range(count)
    ]


def _payload_bytes(encoded) -> int:
    return sum(sum(memoryview(f).nbytes for f in frames[1:]) for frames in encoded)


# --- 1. the writer alone ---------------------------------------------------------------------------


def bench_writer(args, workdir: Path) -> dict:
    from stg_node.bus.recording import BagWriter

    encoded = _encoded(args.frames)
    total = _payload_bytes(encoded)
    results: dict[str, list[float]] = {"raw file write": [], "none": [], "lz4": [], "zstd": []}
    sizes: dict[str, int] = {}
    order = list(results)
    for repeat in range(args.repeats):
        for name in order[repeat % len(order) :] + order[: repeat % len(order)]:
            path = workdir / f"writer-{name.replace(' ', '-')}.mcap"
            start = time.perf_counter()
            if name == "raw file write":
                with open(path, "wb") as f:
                    for frames in encoded:
                        for buf in frames[1:]:
                            f.write(buf)
            else:
                with BagWriter(path, compression=name) as bag:
                    for i, frames in enumerate(encoded):
                        bag.write_frames(frames, time.time_ns() + i)
            seconds = time.perf_counter() - start
            results[name].append(total / seconds / 1e6)
            sizes[name] = path.stat().st_size
            path.unlink()
    base = results["raw file write"]
    out = {}
    for name, rates in results.items():
        ratios = [r / b for r, b in zip(rates, base, strict=True)]
        out[name] = {
            "mb_s": statistics.median(rates),
            "ratio_to_raw": statistics.median(ratios),
            "file_mb": sizes[name] / 1e6,
        }
    return {"payload_mb": total / 1e6, "frames": args.frames, "results": out}


# --- 2. and 3. live, through a broker ---------------------------------------------------------------


def _broker_main(url: str, stop) -> None:
    from stg_node.bus import Broker

    with Broker(url, status_period_s=0):
        stop.wait()


def _publisher_main(url: str, topic: str, count: int, fps: float, go, stop, sent) -> None:
    from stg_node.bus import Publisher

    frames = [_frame(i) for i in range(4)]
    with Publisher(url, node="bench-camera") as pub:
        if not pub.wait_for_subscribers(topic, timeout=30):
            return
        go.wait(60)
        start = time.monotonic()
        for i in range(count):
            if fps > 0:
                due = start + i / fps
                while (left := due - time.monotonic()) > 0:
                    time.sleep(left)
            pub.publish(frames[i % 4], topic)
            sent.value = i + 1
        stop.wait(120)  # LINGER 0: stay until the receiver has everything


def _witness_main(url: str, topic: str, ready, stop, received, lost) -> None:
    """A plain subscriber beside the recorder: tells losses upstream of the broker (both see
    them) from losses of the recorder alone."""
    from stg_node.bus import Subscriber

    with Subscriber(url, [topic], typed=False, keep_last=False) as sub:
        ready.set()
        while not stop.is_set():
            if sub.recv(timeout=0.1) is not None:
                received.value += 1
            lost.value = sub.traffic.drops.get("lost", 0)


class LiveBus:
    def __init__(self, workdir: Path):
        self.ctx = mp.get_context("spawn")
        self.url = f"ipc://{workdir}/bus"
        self.stop = self.ctx.Event()
        self.broker = self.ctx.Process(target=_broker_main, args=(self.url, self.stop), daemon=True)
        self.broker.start()
        time.sleep(1.0)

    def publisher(self, topic: str, count: int, fps: float):
        go, stop, sent = self.ctx.Event(), self.ctx.Event(), self.ctx.Value("l", 0)
        proc = self.ctx.Process(
            target=_publisher_main, args=(self.url, topic, count, fps, go, stop, sent), daemon=True
        )
        proc.start()
        return proc, go, stop, sent

    def witness(self, topic: str):
        ready, stop = self.ctx.Event(), self.ctx.Event()
        received, lost = self.ctx.Value("l", 0), self.ctx.Value("l", 0)
        proc = self.ctx.Process(
            target=_witness_main, args=(self.url, topic, ready, stop, received, lost), daemon=True
        )
        proc.start()
        ready.wait(30)
        return proc, stop, received, lost

    def close(self) -> None:
        self.stop.set()
        self.broker.join(10)


def _record_burst(bus: LiveBus, path: Path, count: int, nbytes_each: int) -> tuple[float, dict]:
    from stg_node.bus.recording import BagReader, Recorder

    proc, go, stop, _sent = bus.publisher(BURST_TOPIC, count, fps=0)
    recorder = Recorder(path, config=bus.url, max_queue_bytes=4 * count * nbytes_each).start()
    go.set()
    deadline = time.monotonic() + 120
    while recorder.stats().written < count and time.monotonic() < deadline:
        recorder.poll(0.05)
    stats = recorder.stop()
    closed_ns = time.time_ns()
    stop.set()
    proc.join(10)
    first_ns = BagReader(path).start_ns
    seconds = (closed_ns - first_ns) / 1e9
    path.unlink()
    return stats.bytes_written / seconds / 1e6, {"written": stats.written, "drops": stats.drops}


def _receive_burst(bus: LiveBus, count: int) -> float:
    from stg_node.bus import Subscriber

    proc, go, stop, _sent = bus.publisher(BURST_TOPIC, count, fps=0)
    received = 0
    nbytes = 0
    with Subscriber(bus.url, [BURST_TOPIC], typed=False) as sub:
        go.set()
        first = None
        while received < count:
            env = sub.recv(timeout=60)
            if env is None:
                break
            first = first or time.time_ns()
            received += 1
            nbytes += env.nbytes
        last = time.time_ns()
    stop.set()
    proc.join(10)
    return nbytes / ((last - first) / 1e9) / 1e6


def bench_live(args, workdir: Path, bus: LiveBus) -> dict:
    nbytes_each = _payload_bytes(_encoded(1))
    rec, sub, ratios, details = [], [], [], []
    for repeat in range(args.repeats):
        pair = ["record", "receive"] if repeat % 2 == 0 else ["receive", "record"]
        got = {}
        for name in pair:
            if name == "record":
                got[name], detail = _record_burst(bus, workdir / "live.mcap", args.frames, nbytes_each)
                details.append(detail)
            else:
                got[name] = _receive_burst(bus, args.frames)
        rec.append(got["record"])
        sub.append(got["receive"])
        ratios.append(got["record"] / got["receive"])
    return {
        "frames": args.frames,
        "record_mb_s": statistics.median(rec),
        "bus_only_mb_s": statistics.median(sub),
        "ratio_record_to_bus_only": statistics.median(ratios),
        "record_runs": rec,
        "bus_only_runs": sub,
        "details": details,
    }


def bench_camera(args, workdir: Path, bus: LiveBus) -> dict:
    from stg_node.bus.recording import BagReader, Recorder

    count = int(round(args.seconds * 30))
    path = workdir / "camera.mcap"
    witness = None
    if args.witness:
        witness, witness_stop, witness_received, witness_lost = bus.witness(CAMERA_TOPIC)
    proc, go, stop, sent = bus.publisher(CAMERA_TOPIC, count, fps=30.0)
    recorder = Recorder(path, config=bus.url).start()
    go.set()
    deadline = time.monotonic() + args.seconds + 30
    while recorder.stats().written < count and time.monotonic() < deadline:
        recorder.poll(0.05)
        if not proc.is_alive() and sent.value < count:
            break
    time.sleep(0.5)
    recorder.poll(0.1)
    stats = recorder.stop()
    stop.set()
    proc.join(10)
    if witness is not None:
        witness_stop.set()
        witness.join(10)
    reader = BagReader(path)
    seqs = [m.sequence for m in reader.messages()]
    path.unlink()
    return {
        "fps": 30,
        "seconds": args.seconds,
        "sent": sent.value,
        "recorded": stats.written,
        "drops": stats.drops,
        "in_order_without_gaps": seqs == list(range(len(seqs))),
        "witness_received": witness_received.value if witness else None,
        "witness_lost": witness_lost.value if witness else None,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=60, help="1080p frames per burst (6.2 MB each)")
    parser.add_argument("--repeats", type=int, default=5, help="alternating repeats per measurement")
    parser.add_argument("--seconds", type=float, default=10.0, help="length of the 30 fps camera run")
    parser.add_argument("--dir", type=Path, help="where to write (default: a temporary folder)")
    parser.add_argument(
        "--witness",
        action="store_true",
        help="camera run: a second plain subscriber (another process) tells upstream losses from the "
        "recorder's own; it also loads the machine",
    )
    parser.add_argument("--skip", nargs="*", default=[], choices=["writer", "live", "camera"])
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args(argv)
    workdir = Path(tempfile.mkdtemp(prefix="stgbag-", dir=args.dir))
    report = {
        "machine": f"{platform.node()} {platform.machine()}, {os.cpu_count()} cpus, "
        f"python {platform.python_version()}",
        "load_before": os.getloadavg(),
        "dir": str(workdir),
    }
    try:
        if "writer" not in args.skip:
            report["writer"] = bench_writer(args, workdir)
            print("writer (MB/s, ratio to raw file write of the same bytes, file MB):")
            for name, r in report["writer"]["results"].items():
                print(f"  {name:15s} {r['mb_s']:8.0f}  x{r['ratio_to_raw']:.2f}  {r['file_mb']:.0f} MB")
        if "live" not in args.skip or "camera" not in args.skip:
            bus = LiveBus(workdir)
            try:
                if "live" not in args.skip:
                    live = report["live"] = bench_live(args, workdir, bus)
                    print(
                        f"live burst of {live['frames']} frames through a broker: record "
                        f"{live['record_mb_s']:.0f} MB/s, bus only {live['bus_only_mb_s']:.0f} MB/s, "
                        f"ratio x{live['ratio_record_to_bus_only']:.2f}; drops "
                        f"{[d['drops'] for d in live['details']]}"
                    )
                if "camera" not in args.skip:
                    cam = report["camera"] = bench_camera(args, workdir, bus)
                    print(
                        f"camera 30 fps 1080p for {cam['seconds']:g} s: sent {cam['sent']}, recorded "
                        f"{cam['recorded']}, drops {cam['drops'] or 0}, in order without gaps: "
                        f"{cam['in_order_without_gaps']}"
                        + (
                            f"; a plain subscriber beside it received {cam['witness_received']}, "
                            f"lost {cam['witness_lost']}"
                            if args.witness
                            else ""
                        )
                    )
            finally:
                bus.close()
        report["load_after"] = os.getloadavg()
        print(f"load average before {report['load_before'][0]:.2f}, after {report['load_after'][0]:.2f}")
        if args.json:
            args.json.write_text(json.dumps(report, indent=2))
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
