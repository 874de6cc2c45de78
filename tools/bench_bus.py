#!/usr/bin/env python3
"""Our Publisher/Subscriber against raw pyzmq + msgpack, paired in one run: throughput and latency.

Implementations compared (all carrying the same frames: [topic, msgpack header, image, K, R, t]):

- raw:          pyzmq PUB -> SUB with the same socket options as ours (LINGER 0, the reliable
                lane's HWMs, MAXMSGSIZE); the header packed and unpacked by hand (msgpack +
                np.frombuffer), exactly as proto/README.md shows a robot doing it;
- ours:         stg_node.bus Publisher(bind=True) -> Subscriber on the reliable lane: a typed
                Frame, fully validated on both sides, counted, sequence-checked;
- ours-latest:  the same on the keep-last lane (camera/frame), through the subscriber's
                reader thread; latency only (keep-last skips messages by design);
- with --broker: ours direct, ours through a Broker process, and raw through zmq.proxy (C).

Fairness on a loaded machine: for each transport and size, ONE sender process and ONE
receiver process host every implementation side by side. Throughput bursts alternate
between implementations (the order rotates every repeat), and latency pings alternate
message by message, so a change in machine load hits all of them alike.

Throughput: a burst of N messages back to back; MB/s = N * size / (receipt of the last -
send of the first), on the monotonic clock both processes share. Latency: one message in
flight; one-way = receipt after decoding - send before encoding; median over the pings.

    python tools/bench_bus.py [--repeats 5] [--broker] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import platform
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import msgpack  # noqa: E402
import numpy as np  # noqa: E402
import zmq  # noqa: E402

SIZES = {"1MB": (512, 683), "6MB": (1080, 1920)}  # H, W of an RGB uint8 image
TOPIC = "bench/frame"  # a custom topic: the reliable lane
LATEST_TOPIC = "camera/frame"  # the keep-last lane
WARM = "bench/warm"


def _new_url(transport: str, workdir: str, name: str) -> str:
    from stg_node.bus.config import free_tcp_base_port

    if transport == "ipc":
        return f"ipc://{workdir}/{name}"
    return f"tcp://127.0.0.1:{free_tcp_base_port()}"


def _socket_options(sock: zmq.Socket) -> None:
    """The reliable lane's options, applied to the raw sockets exactly as ours apply them."""
    from stg_node.bus.sockets import MAX_MESSAGE_BYTES
    from stg_node.bus.topics import LANES

    sock.linger = 0
    sock.sndhwm = LANES["reliable"].hwm
    sock.rcvhwm = LANES["reliable"].hwm
    if sock.type in (zmq.SUB, zmq.XSUB):
        sock.maxmsgsize = MAX_MESSAGE_BYTES


# --- the implementations, as (sender, receiver) pairs --------------------------------------------


def _impl_specs(names: list[str], transport: str, workdir: str, brokers: dict[str, str]) -> dict[str, dict]:
    """Where each implementation's messages go. 'ours' and 'ours-latest' share one bus."""
    from stg_node.bus.config import lane_endpoint

    own = _new_url(transport, workdir, f"own-{transport}")
    raw = _new_url(transport, workdir, f"raw-{transport}")
    specs = {}
    for name in names:
        if name == "raw":
            specs[name] = {
                "kind": "raw",
                "url": raw,
                "bind": True,
                "topic": TOPIC,
                "pub": lane_endpoint(raw, "reliable", "out"),
                "sub": lane_endpoint(raw, "reliable", "out"),
            }
        elif name in ("ours", "ours-latest"):
            specs[name] = {
                "kind": "ours",
                "url": own,
                "bind": True,
                "topic": LATEST_TOPIC if name == "ours-latest" else TOPIC,
            }
        elif name == "ours+broker":
            specs[name] = {"kind": "ours", "url": brokers["ours"], "bind": False, "topic": TOPIC}
        elif name == "raw+proxy":
            url = brokers["raw"]
            specs[name] = {
                "kind": "raw",
                "url": url,
                "bind": False,
                "topic": TOPIC,
                "pub": lane_endpoint(url, "reliable", "in"),
                "sub": lane_endpoint(url, "reliable", "out"),
            }
    return specs


def _raw_decode(frames):
    header = msgpack.unpackb(frames[1].buffer)
    arrays = {
        d["name"]: np.frombuffer(f.buffer, dtype=d["dtype"]).reshape(d["shape"])
        for d, f in zip(header["arrays"], frames[2:], strict=True)
    }
    return frames[0].bytes.decode(), arrays["image"]


def _receiver(specs: dict[str, dict], ctrl_in: str, ctrl_out: str) -> None:
    """Child process: waits for commands, receives on the named implementation, reports."""
    from stg_node.bus import BusConfig, Subscriber

    ctx = zmq.Context()
    commands = ctx.socket(zmq.PULL)
    commands.linger = 0
    commands.connect(ctrl_in)
    replies = ctx.socket(zmq.PUSH)
    replies.linger = 0
    replies.connect(ctrl_out)
    receivers, closers = {}, []
    try:
        for name, spec in specs.items():
            if spec["kind"] == "ours":
                sub = Subscriber(BusConfig(url=spec["url"]), [spec["topic"], WARM], context=ctx)
                closers.append(sub.close)

                def recv(sub=sub):
                    msg = sub.recv(timeout=20.0)
                    if msg is None:
                        raise TimeoutError("receiver timed out")
                    return msg.header.topic, msg.image

            else:
                sock = ctx.socket(zmq.SUB)
                _socket_options(sock)
                sock.connect(spec["sub"])
                sock.subscribe(TOPIC.encode())
                sock.subscribe(WARM.encode())

                def recv(sock=sock):
                    if not sock.poll(20_000):
                        raise TimeoutError("receiver timed out")
                    return _raw_decode(sock.recv_multipart(copy=False))

            receivers[name] = recv
        replies.send_pyobj(("ready", 0))
        while True:
            if not commands.poll(60_000):
                raise TimeoutError("no command for 60 s")
            command, name, count = commands.recv_pyobj()
            if command == "quit":
                break
            recv, topic = receivers[name], specs[name]["topic"]
            if command == "warm":
                while recv()[0] != WARM:
                    pass
                replies.send_pyobj(("warm", 0))
                continue
            got = 0
            while got < count:
                if recv()[0] == topic:  # warm-up stragglers are skipped
                    got += 1
            replies.send_pyobj((command, time.perf_counter_ns()))
    except Exception as exc:  # report, do not leave the parent waiting
        replies.send_pyobj(("error", repr(exc)))
    finally:
        for close in closers:
            close()
        replies.close(0)
        commands.close(0)
        ctx.term()


class Session:
    """One sender (this process) and one receiver process hosting every implementation."""

    def __init__(self, specs: dict[str, dict], size: str, workdir: str, index: int):
        from stg_node.bus import BusConfig, Frame, Publisher

        self.specs = specs
        self.ctx = zmq.Context()
        self.commands = self.ctx.socket(zmq.PUSH)
        self.commands.linger = 0
        ctrl_in = f"ipc://{workdir}/cmd{index}"
        self.commands.bind(ctrl_in)
        self.replies = self.ctx.socket(zmq.PULL)
        self.replies.linger = 0
        ctrl_out = f"ipc://{workdir}/rep{index}"
        self.replies.bind(ctrl_out)
        self.child = mp.get_context("spawn").Process(
            target=_receiver, args=(specs, ctrl_in, ctrl_out), daemon=True
        )
        self.child.start()
        h, w = SIZES[size]
        self.image = np.full((h, w, 3), 7, np.uint8)
        self.nbytes = self.image.nbytes
        K, R, t = np.eye(3), np.eye(3), np.array([0.0, 0.0, 2.0])
        warm_image = np.zeros((4, 4, 3), np.uint8)
        self.senders, self._publishers, self.warm = {}, {}, {}
        for name, spec in specs.items():
            if spec["kind"] == "ours":
                key = (spec["url"], spec["bind"])
                pub = self._publishers.get(key)
                if pub is None:
                    pub = self._publishers[key] = Publisher(
                        BusConfig(url=spec["url"]), node="bench", context=self.ctx, bind=spec["bind"]
                    )

                def send(img, seq, topic, pub=pub):
                    pub.publish(Frame(index=seq, image=img, K=K, R=R, t=t), topic)
            else:
                sock = self.ctx.socket(zmq.PUB)
                _socket_options(sock)
                (sock.bind if spec["bind"] else sock.connect)(spec["pub"])
                names = {TOPIC: TOPIC.encode(), WARM: WARM.encode()}

                def send(img, seq, topic, sock=sock, names=names):
                    header = {
                        "type": "Frame",
                        "v": 1,
                        "seq": seq,
                        "stamp_ns": time.time_ns(),
                        "src": "bench",
                        "index": seq,
                        "time": 0.0,
                        "camera_id": "",
                        "arrays": [
                            {"name": "image", "dtype": "uint8", "shape": list(img.shape)},
                            {"name": "K", "dtype": "float64", "shape": [3, 3]},
                            {"name": "R", "dtype": "float64", "shape": [3, 3]},
                            {"name": "t", "dtype": "float64", "shape": [3]},
                        ],
                    }
                    sock.send_multipart([names[topic], msgpack.packb(header), img, K, R, t], copy=False)

            self.senders[name] = send
            self.warm[name] = warm_image
        self._expect("ready", 60_000)
        for name in specs:
            self._warm_up(name)
        self.seq = 0

    def _expect(self, kind: str, timeout_ms: int = 60_000):
        if not self.replies.poll(timeout_ms):
            raise TimeoutError(f"no {kind!r} from the receiver")
        what, value = self.replies.recv_pyobj()
        if what == "error":
            raise RuntimeError(f"receiver failed: {value}")
        if what != kind:
            raise RuntimeError(f"expected {kind!r} from the receiver, got {what!r}")
        return value

    def _warm_up(self, name: str) -> None:
        """Until the receiver has seen this implementation's warm-up topic: subscriptions are in."""
        self.commands.send_pyobj(("warm", name, 0))
        deadline = time.monotonic() + 30
        while not self.replies.poll(10):
            self.senders[name](self.warm[name], 0, WARM)
            if time.monotonic() > deadline:
                raise TimeoutError(f"{name}: the subscription never arrived")
        self._expect("warm")
        if self.specs[name]["topic"] != TOPIC:  # its data topic is on another lane: wait for it too
            pub = next(iter(self._publishers.values()))
            if not pub.wait_for_subscribers(self.specs[name]["topic"], timeout=30):
                raise TimeoutError(f"{name}: no subscription to {self.specs[name]['topic']}")

    def burst(self, name: str, n: int) -> float:
        """MB/s of ``n`` back-to-back messages."""
        send, topic = self.senders[name], self.specs[name]["topic"]
        self.commands.send_pyobj(("burst", name, n))
        start = time.perf_counter_ns()
        for _ in range(n):
            send(self.image, self.seq, topic)
            self.seq += 1
        end = self._expect("burst", 120_000)
        return n * self.nbytes / ((end - start) / 1e9) / 1e6

    def ping(self, name: str) -> float:
        """One-way latency of one message, microseconds."""
        send, topic = self.senders[name], self.specs[name]["topic"]
        self.commands.send_pyobj(("ping", name, 1))
        time.sleep(0.0005)  # let the receiver pick the command up first
        start = time.perf_counter_ns()
        send(self.image, self.seq, topic)
        self.seq += 1
        return (self._expect("ping") - start) / 1e3

    def close(self) -> None:
        try:
            self.commands.send_pyobj(("quit", "", 0))
        except zmq.ZMQError:
            pass
        self.child.join(10)
        if self.child.is_alive():
            self.child.kill()
        for pub in self._publishers.values():
            pub.close()
        self.ctx.destroy(0)


def _broker_process(kind: str, url: str, stop_path: str) -> None:
    if kind == "ours":
        from stg_node.bus import Broker

        with Broker(url, status_period_s=0):
            while not os.path.exists(stop_path):
                time.sleep(0.05)
        return
    from stg_node.bus.config import lane_endpoint  # raw: zmq's C proxy on the reliable lane

    ctx = zmq.Context()
    xsub, xpub = ctx.socket(zmq.XSUB), ctx.socket(zmq.XPUB)
    _socket_options(xsub)
    _socket_options(xpub)
    xsub.bind(lane_endpoint(url, "reliable", "in"))
    xpub.bind(lane_endpoint(url, "reliable", "out"))
    control, steer = ctx.socket(zmq.PAIR), ctx.socket(zmq.PAIR)
    control.bind("inproc://ctl")
    steer.connect("inproc://ctl")

    def watch():
        while not os.path.exists(stop_path):
            time.sleep(0.05)
        control.send(b"TERMINATE")

    threading.Thread(target=watch, daemon=True).start()
    zmq.proxy_steerable(xsub, xpub, None, steer)
    for s in (xsub, xpub, control, steer):
        s.close(0)
    ctx.term()


def run_session(names, transport, size, args, workdir, index, brokers=None) -> list[dict]:
    """Every implementation in ``names`` measured side by side; rows tagged with the session."""
    session_name = "broker" if brokers else "direct"
    specs = _impl_specs(names, transport, workdir, brokers or {})
    session = Session(specs, size, workdir, index)
    rows = []
    n = args.n1 if size == "1MB" else args.n6
    try:
        timed = [name for name in names if name != "ours-latest"]
        for name in timed:  # untimed: first-touch costs (buffers, page faults) hit nobody's figures
            session.burst(name, n)
        for rep in range(args.repeats):
            order = timed[rep % len(timed) :] + timed[: rep % len(timed)]
            for name in order:
                rows.append(
                    {
                        "session": session_name,
                        "impl": name,
                        "transport": transport,
                        "size": size,
                        "repeat": rep,
                        "MB_s": session.burst(name, n),
                    }
                )
        pings: dict[str, list[float]] = {name: [] for name in names}
        for i in range(args.lat):
            for name in names[i % len(names) :] + names[: i % len(names)]:
                pings[name].append(session.ping(name))
        for name, values in pings.items():
            rows.append(
                {
                    "session": session_name,
                    "impl": name,
                    "transport": transport,
                    "size": size,
                    "lat_us": values,
                }
            )
    finally:
        session.close()
    return rows


def _throughputs(rows, impl, transport, size) -> list[float]:
    picked = [
        r
        for r in rows
        if r["impl"] == impl and r["transport"] == transport and r["size"] == size and "MB_s" in r
    ]
    return [r["MB_s"] for r in sorted(picked, key=lambda r: r["repeat"])]


def _latency_ms(rows, impl, transport, size) -> float:
    for r in rows:
        if r["impl"] == impl and r["transport"] == transport and r["size"] == size and "lat_us" in r:
            return statistics.median(r["lat_us"]) / 1e3
    return float("nan")


def _paired_added_ms(rows, impl, base, transport, size) -> float:
    """Median of per-ping differences: pings alternate, so neighbours saw the same load."""
    a = next(
        r["lat_us"]
        for r in rows
        if r["impl"] == impl and r["transport"] == transport and r["size"] == size and "lat_us" in r
    )
    b = next(
        r["lat_us"]
        for r in rows
        if r["impl"] == base and r["transport"] == transport and r["size"] == size and "lat_us" in r
    )
    return statistics.median(x - y for x, y in zip(a, b, strict=True)) / 1e3


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=7, help="throughput bursts per implementation")
    parser.add_argument("--n1", type=int, default=200, help="messages per burst at 1 MB")
    parser.add_argument("--n6", type=int, default=40, help="messages per burst at 6 MB")
    parser.add_argument("--lat", type=int, default=300, help="latency pings per implementation")
    parser.add_argument("--transports", nargs="+", default=["ipc", "tcp"])
    parser.add_argument("--sizes", nargs="+", default=list(SIZES))
    parser.add_argument("--broker", action="store_true", help="also measure through a broker")
    parser.add_argument("--json", type=Path, help="write every measurement here")
    args = parser.parse_args(argv)

    from stg_node.logs import configure_logging

    configure_logging("WARNING")
    workdir = tempfile.mkdtemp(prefix="stgbench-")
    rows: list[dict] = []
    index = 0
    load_before = os.getloadavg()[0]
    print(f"# bench_bus: {platform.node()}, {os.cpu_count()} cores, load {load_before:.2f}", flush=True)
    for transport in args.transports:
        for size in args.sizes:
            index += 1
            rows += run_session(["raw", "ours", "ours-latest"], transport, size, args, workdir, index)
            raw_mb = statistics.median(_throughputs(rows, "raw", transport, size))
            ours_mb = statistics.median(_throughputs(rows, "ours", transport, size))
            print(f"  {transport} {size}: raw {raw_mb:.0f} ours {ours_mb:.0f} MB/s", flush=True)
    if args.broker:
        for transport in args.transports:
            urls = {kind: _new_url(transport, workdir, f"broker-{kind}") for kind in ("ours", "raw")}
            stop = f"{workdir}/stop-{transport}"
            procs = [
                mp.get_context("spawn").Process(target=_broker_process, args=(kind, url, stop), daemon=True)
                for kind, url in urls.items()
            ]
            for proc in procs:
                proc.start()
            time.sleep(1.5)
            try:
                for size in args.sizes:
                    index += 1
                    rows += run_session(
                        ["ours", "ours+broker", "raw+proxy"],
                        transport,
                        size,
                        args,
                        workdir,
                        index,
                        brokers=urls,
                    )
                    print(f"  {transport} {size}: broker session done", flush=True)
            finally:
                Path(stop).touch()
                for proc in procs:
                    proc.join(5)
                    if proc.is_alive():
                        proc.kill()

    load_after = os.getloadavg()[0]
    print(f"\nload average: {load_before:.2f} before, {load_after:.2f} after (of {os.cpu_count()} cores)")
    print(
        "\n| transport | size | raw MB/s | ours MB/s | ratio (median of paired bursts) | raw latency ms "
        "| ours latency ms | added ms (median of paired pings) | ours keep-last latency ms | added ms |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    summary = []
    direct = [r for r in rows if r["session"] == "direct"]
    for transport in args.transports:
        for size in args.sizes:
            raw = _throughputs(direct, "raw", transport, size)
            ours = _throughputs(direct, "ours", transport, size)
            entry = {
                "transport": transport,
                "size": size,
                "raw_MB_s": statistics.median(raw),
                "ours_MB_s": statistics.median(ours),
                "ratio": statistics.median(o / r for o, r in zip(ours, raw, strict=True)),
                "raw_lat_ms": _latency_ms(direct, "raw", transport, size),
                "ours_lat_ms": _latency_ms(direct, "ours", transport, size),
                "added_ms": _paired_added_ms(direct, "ours", "raw", transport, size),
                "latest_lat_ms": _latency_ms(direct, "ours-latest", transport, size),
                "latest_added_ms": _paired_added_ms(direct, "ours-latest", "raw", transport, size),
            }
            summary.append(entry)
            print(
                f"| {transport} | {size} | {entry['raw_MB_s']:.0f} | {entry['ours_MB_s']:.0f} | "
                f"{entry['ratio']:.2f} | {entry['raw_lat_ms']:.3f} | {entry['ours_lat_ms']:.3f} | "
                f"{entry['added_ms']:+.3f} | {entry['latest_lat_ms']:.3f} | {entry['latest_added_ms']:+.3f} |"
            )
    if args.broker:
        block = [r for r in rows if r["session"] == "broker"]
        print(
            "\n| transport | size | ours direct MB/s | ours + broker MB/s | raw + C proxy MB/s "
            "| ours direct latency ms | ours + broker ms | raw + C proxy ms | broker adds ms (paired) |"
        )
        print("|---|---|---|---|---|---|---|---|---|")
        for transport in args.transports:
            for size in args.sizes:

                def mb(impl, transport=transport, size=size):
                    return statistics.median(_throughputs(block, impl, transport, size))

                def ms(impl, transport=transport, size=size):
                    return _latency_ms(block, impl, transport, size)

                added = _paired_added_ms(block, "ours+broker", "ours", transport, size)
                print(
                    f"| {transport} | {size} | {mb('ours'):.0f} | {mb('ours+broker'):.0f} | "
                    f"{mb('raw+proxy'):.0f} | {ms('ours'):.3f} | {ms('ours+broker'):.3f} | "
                    f"{ms('raw+proxy'):.3f} | {added:+.3f} |"
                )
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "summary": summary}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
