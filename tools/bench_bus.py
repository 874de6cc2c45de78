#!/usr/bin/env python3
"""Our Publisher/Subscriber against raw pyzmq + msgpack, in one run: throughput and latency.

For each transport (ipc, tcp) and message size (1 MB, 6 MB = one 1080p RGB frame) it runs,
interleaved and repeated (the order alternates every repeat, so load changes on a shared
machine hit both sides alike):

- raw:   PUB -> SUB with the same socket options (LINGER 0, the reliable lane's HWMs,
         MAXMSGSIZE), the same frames [topic, msgpack header, image, K, R, t] packed and
         unpacked by hand (msgpack + np.frombuffer), as proto/README.md shows;
- ours:  stg_node.bus Publisher(bind=True) -> Subscriber, a typed Frame, fully validated;
- broker (with --broker): ours through a Broker process, and raw through zmq.proxy (C) for
         reference.

Throughput: the sender publishes N messages back to back; the receiver (another process)
timestamps the last one; MB/s = N * size / (last receipt - first send) on the shared
monotonic clock. Latency: ping-pong, one message in flight; one-way = receipt (after
decoding) - send (before encoding); the median over L messages.

    python tools/bench_bus.py [--repeats 5] [--broker] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import platform
import socket
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import msgpack  # noqa: E402
import numpy as np  # noqa: E402
import zmq  # noqa: E402

SIZES = {"1MB": (512, 683), "6MB": (1080, 1920)}  # H, W of an RGB uint8 image
TOPIC = "bench/frame"
WARM = "bench/warm"


def _free_base_port(span: int = 6) -> int:
    for _ in range(200):
        with socket.socket() as probe:
            probe.bind(("127.0.0.1", 0))
            base = probe.getsockname()[1]
        if base + span >= 65535:
            continue
        ok = True
        for port in range(base, base + span):
            with socket.socket() as s:
                try:
                    s.bind(("127.0.0.1", port))
                except OSError:
                    ok = False
                    break
        if ok:
            return base
    raise RuntimeError("no free tcp port range")


def _socket_options(sock: zmq.Socket) -> None:
    """The reliable lane's options, applied to the raw sockets exactly as ours apply them."""
    from stg_node.bus.sockets import MAX_MESSAGE_BYTES
    from stg_node.bus.topics import LANES

    sock.linger = 0
    sock.sndhwm = LANES["reliable"].hwm
    sock.rcvhwm = LANES["reliable"].hwm
    if sock.type in (zmq.SUB, zmq.XSUB):
        sock.maxmsgsize = MAX_MESSAGE_BYTES


def _frame_arrays(size: str, fill: int = 7):
    h, w = SIZES[size]
    image = np.full((h, w, 3), fill, np.uint8)
    return image, np.eye(3), np.eye(3), np.array([0.0, 0.0, 2.0])


# --- receiver process ----------------------------------------------------------------------------


def _topic(impl: str) -> str:
    """ours-latest goes through the keep-last lane (camera/frame) and its reader thread."""
    return "camera/frame" if impl == "ours-latest" else TOPIC


def _receiver(impl: str, url: str, endpoint: str, ctrl: str, n: int, lat_n: int) -> None:
    topic_name = _topic(impl)
    ctx = zmq.Context()
    push = ctx.socket(zmq.PUSH)
    push.linger = 0
    push.connect(ctrl)
    sub = None
    try:
        if impl.startswith("ours"):
            from stg_node.bus import BusConfig, Subscriber

            sub = Subscriber(BusConfig(url=url), [topic_name, WARM], context=ctx)

            def recv():
                msg = sub.recv(timeout=20.0)
                if msg is None:
                    raise TimeoutError("receiver timed out")
                return msg.header.topic, msg.image
        else:
            sock = ctx.socket(zmq.SUB)
            _socket_options(sock)
            sock.connect(endpoint)
            sock.subscribe(TOPIC.encode())
            sock.subscribe(WARM.encode())

            def recv():
                if not sock.poll(20_000):
                    raise TimeoutError("receiver timed out")
                frames = sock.recv_multipart(copy=False)
                header = msgpack.unpackb(frames[1].buffer)
                arrays = {
                    d["name"]: np.frombuffer(f.buffer, dtype=d["dtype"]).reshape(d["shape"])
                    for d, f in zip(header["arrays"], frames[2:], strict=True)
                }
                return frames[0].bytes.decode(), arrays["image"]

        push.send_pyobj(("ready", 0))
        warm_sent = False
        got = 0
        while not warm_sent or got < n:
            topic, image = recv()
            if topic == WARM:
                if not warm_sent:
                    push.send_pyobj(("warm", 0))
                    warm_sent = True
                continue
            got += 1
        push.send_pyobj(("done", time.perf_counter_ns()))
        for _ in range(lat_n):
            topic, image = recv()
            while topic != topic_name:
                topic, image = recv()
            push.send_pyobj(("lat", time.perf_counter_ns()))
    except Exception as exc:  # report, do not hang the parent
        push.send_pyobj(("error", repr(exc)))
    finally:
        if sub is not None:
            sub.close()
        push.close(0)
        ctx.destroy(0)


# --- broker processes ------------------------------------------------------------------------------


def _broker_process(kind: str, url: str, stop_path: str) -> None:
    if kind == "ours":
        from stg_node.bus import Broker

        with Broker(url, status_period_s=0):
            while not os.path.exists(stop_path):
                time.sleep(0.05)
    else:  # C proxy on the reliable lane, same options
        from stg_node.bus.config import lane_endpoint

        ctx = zmq.Context()
        xsub, xpub = ctx.socket(zmq.XSUB), ctx.socket(zmq.XPUB)
        _socket_options(xsub)
        _socket_options(xpub)
        xsub.bind(lane_endpoint(url, "reliable", "in"))
        xpub.bind(lane_endpoint(url, "reliable", "out"))
        ctl_pub = ctx.socket(zmq.PAIR)
        ctl_pub.bind("inproc://ctl")
        ctl_sub = ctx.socket(zmq.PAIR)
        ctl_sub.connect("inproc://ctl")

        import threading

        def watch():
            while not os.path.exists(stop_path):
                time.sleep(0.05)
            ctl_pub.send(b"TERMINATE")

        threading.Thread(target=watch, daemon=True).start()
        zmq.proxy_steerable(xsub, xpub, None, ctl_sub)
        for s in (xsub, xpub, ctl_pub, ctl_sub):
            s.close(0)
        ctx.term()


# --- one trial -------------------------------------------------------------------------------------


def trial(
    impl: str,
    transport: str,
    size: str,
    n: int,
    lat_n: int,
    workdir: str,
    index: int,
    broker_url: str | None = None,
) -> dict:
    from stg_node.bus import BusConfig, Frame, Publisher
    from stg_node.bus.config import lane_endpoint

    if broker_url is not None:
        url = broker_url
    elif transport == "ipc":
        url = f"ipc://{workdir}/t{index}"
    else:
        url = f"tcp://127.0.0.1:{_free_base_port()}"
    via_broker = broker_url is not None
    sub_endpoint = lane_endpoint(url, "reliable", "out")
    pub_endpoint = lane_endpoint(url, "reliable", "in" if via_broker else "out")
    ctrl = f"ipc://{workdir}/ctrl{index}"

    ctx = zmq.Context()
    pull = ctx.socket(zmq.PULL)
    pull.linger = 0
    pull.bind(ctrl)
    child = mp.get_context("spawn").Process(
        target=_receiver, args=(impl, url, sub_endpoint, ctrl, n, lat_n), daemon=True
    )
    child.start()

    image, K, R, t = _frame_arrays(size)
    warm_image, *_ = _frame_arrays("1MB")
    warm_image = warm_image[:4, :4].copy()

    def expect(kind: str, timeout_ms: int = 30_000):
        if not pull.poll(timeout_ms):
            raise TimeoutError(f"no {kind!r} from the receiver")
        what, value = pull.recv_pyobj()
        if what == "error":
            raise RuntimeError(f"receiver failed: {value}")
        if what != kind:
            raise RuntimeError(f"expected {kind!r} from the receiver, got {what!r}")
        return value

    try:
        if impl.startswith("ours"):
            lanes = ["reliable", "latest"] if impl == "ours-latest" else ["reliable"]
            pub = Publisher(BusConfig(url=url), node="bench", context=ctx, bind=not via_broker, lanes=lanes)
            data_topic = _topic(impl)

            def send(topic: str, img: np.ndarray, seq: int) -> None:
                pub.publish(
                    Frame(index=seq, image=img, K=K, R=R, t=t), data_topic if topic == TOPIC else topic
                )
        else:
            sock = ctx.socket(zmq.PUB)
            _socket_options(sock)
            (sock.connect if via_broker else sock.bind)(pub_endpoint)
            topics = {TOPIC: TOPIC.encode(), WARM: WARM.encode()}

            def send(topic: str, img: np.ndarray, seq: int) -> None:
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
                sock.send_multipart([topics[topic], msgpack.packb(header), img, K, R, t], copy=False)

        expect("ready")
        if impl.startswith("ours") and not pub.wait_for_subscribers(data_topic, timeout=20):
            raise TimeoutError(f"no subscription to {data_topic}")
        deadline = time.monotonic() + 20
        while not pull.poll(10):  # warm up until the subscription has propagated
            send(WARM, warm_image, 0)
            if time.monotonic() > deadline:
                raise TimeoutError("subscription never arrived")
        expect("warm")
        # Fresh arrays per message would measure numpy allocation; the camera's buffers are
        # reused the same way by both sides here.
        start = time.perf_counter_ns()
        for i in range(n):
            send(TOPIC, image, i)
        end = expect("done", 120_000)
        mb_s = n * image.nbytes / ((end - start) / 1e9) / 1e6 if n else float("nan")
        lat = []
        for i in range(lat_n):
            t0 = time.perf_counter_ns()
            send(TOPIC, image, n + i)
            lat.append((expect("lat") - t0) / 1e3)
        return {
            "impl": impl,
            "transport": transport,
            "size": size,
            "MB_s": mb_s,
            "lat_median_us": statistics.median(lat),
            "lat_p90_us": float(np.percentile(lat, 90)),
        }
    finally:
        child.join(5)
        if child.is_alive():
            child.kill()
        ctx.destroy(0)


def _median(rows, key):
    return statistics.median(r[key] for r in rows)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--n1", type=int, default=300, help="messages per throughput trial at 1 MB")
    parser.add_argument("--n6", type=int, default=80, help="messages per throughput trial at 6 MB")
    parser.add_argument("--lat", type=int, default=200, help="ping-pong messages per latency trial")
    parser.add_argument("--transports", nargs="+", default=["ipc", "tcp"])
    parser.add_argument("--sizes", nargs="+", default=list(SIZES))
    parser.add_argument("--broker", action="store_true", help="also measure through a broker")
    parser.add_argument("--json", type=Path, help="write all trials here")
    args = parser.parse_args(argv)

    from stg_node.logs import configure_logging

    configure_logging("WARNING")
    workdir = tempfile.mkdtemp(prefix="stgbench-")
    rows: list[dict] = []
    index = 0
    counts = {"1MB": args.n1, "6MB": args.n6}
    print(
        f"# bench_bus: {platform.node()}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}", flush=True
    )
    for rep in range(args.repeats):
        for transport in args.transports:
            for size in args.sizes:
                order = ["raw", "ours", "ours-latest"]
                order = order[rep % 3 :] + order[: rep % 3]  # rotate: no side always goes first
                for impl in order:
                    index += 1
                    n = 0 if impl == "ours-latest" else counts[size]  # keep-last: latency only
                    row = trial(impl, transport, size, n, args.lat, workdir, index)
                    row["repeat"] = rep
                    rows.append(row)
                    print(
                        f"  rep {rep} {transport} {size} {impl:11s} {row['MB_s']:8.0f} MB/s "
                        f"lat {row['lat_median_us']:7.0f} us",
                        flush=True,
                    )
    if args.broker:
        for transport in args.transports:
            for kind in ("ours", "raw"):
                if transport == "ipc":
                    url = f"ipc://{workdir}/broker-{kind}"
                else:
                    url = f"tcp://127.0.0.1:{_free_base_port()}"
                stop = f"{workdir}/stop-{kind}-{transport}"
                proc = mp.get_context("spawn").Process(
                    target=_broker_process, args=(kind, url, stop), daemon=True
                )
                proc.start()
                time.sleep(1.0)
                try:
                    for rep in range(max(1, args.repeats // 2 + 1)):
                        for size in args.sizes:
                            index += 1
                            impl = "ours+broker" if kind == "ours" else "raw+proxy"
                            row = trial(
                                impl, transport, size, counts[size], args.lat, workdir, index, broker_url=url
                            )
                            row["repeat"] = rep
                            rows.append(row)
                            print(
                                f"  rep {rep} {transport} {size} {impl:11s} {row['MB_s']:8.0f} MB/s "
                                f"lat {row['lat_median_us']:7.0f} us",
                                flush=True,
                            )
                finally:
                    Path(stop).touch()
                    proc.join(5)
                    if proc.is_alive():
                        proc.kill()

    print(f"\nload average after: {os.getloadavg()[0]:.2f} (of {os.cpu_count()} cores)")
    print(
        "\n| transport | size | raw MB/s | ours MB/s | ratio (median of paired) | raw lat ms | ours lat ms "
        "| added ms | ours keep-last lat ms | added ms |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    summary = []
    for transport in args.transports:
        for size in args.sizes:

            def pick(impl, transport=transport, size=size):
                return sorted(
                    (
                        r
                        for r in rows
                        if r["impl"] == impl and r["transport"] == transport and r["size"] == size
                    ),
                    key=lambda r: r["repeat"],
                )

            raw, ours, latest = pick("raw"), pick("ours"), pick("ours-latest")
            paired = statistics.median(o["MB_s"] / r["MB_s"] for r, o in zip(raw, ours, strict=True))
            entry = {
                "transport": transport,
                "size": size,
                "raw_MB_s": _median(raw, "MB_s"),
                "ours_MB_s": _median(ours, "MB_s"),
                "ratio": paired,
                "raw_lat_ms": _median(raw, "lat_median_us") / 1e3,
                "ours_lat_ms": _median(ours, "lat_median_us") / 1e3,
                "latest_lat_ms": _median(latest, "lat_median_us") / 1e3,
            }
            entry["added_ms"] = entry["ours_lat_ms"] - entry["raw_lat_ms"]
            entry["latest_added_ms"] = entry["latest_lat_ms"] - entry["raw_lat_ms"]
            summary.append(entry)
            print(
                f"| {transport} | {size} | {entry['raw_MB_s']:.0f} | {entry['ours_MB_s']:.0f} | "
                f"{entry['ratio']:.2f} | {entry['raw_lat_ms']:.3f} | {entry['ours_lat_ms']:.3f} | "
                f"{entry['added_ms']:+.3f} | {entry['latest_lat_ms']:.3f} | {entry['latest_added_ms']:+.3f} |"
            )
    if args.broker:
        print(
            "\n| transport | size | ours direct MB/s | ours+broker MB/s | raw+C proxy MB/s | "
            "ours direct lat ms | ours+broker lat ms | raw+C proxy lat ms |"
        )
        print("|---|---|---|---|---|---|---|---|")
        for transport in args.transports:
            for size in args.sizes:

                def pick(impl, transport=transport, size=size):
                    return [
                        r
                        for r in rows
                        if r["impl"] == impl and r["transport"] == transport and r["size"] == size
                    ]

                d, b, p = pick("ours"), pick("ours+broker"), pick("raw+proxy")
                print(
                    f"| {transport} | {size} | {_median(d, 'MB_s'):.0f} | {_median(b, 'MB_s'):.0f} | "
                    f"{_median(p, 'MB_s'):.0f} | {_median(d, 'lat_median_us') / 1e3:.3f} | "
                    f"{_median(b, 'lat_median_us') / 1e3:.3f} | {_median(p, 'lat_median_us') / 1e3:.3f} |"
                )
    if args.json:
        args.json.write_text(json.dumps({"trials": rows, "summary": summary}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
