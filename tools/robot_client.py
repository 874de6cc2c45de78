#!/usr/bin/env python3
"""A robot stack's view of stg_node, with nothing of ours: raw pyzmq + msgpack + numpy (proto/README.md).

Subscribes to avatar/image, asks for a view on avatar/view, and saves what it receives:
PNG images and one JSON line per image (request id, snapshot version, latencies).

    python tools/robot_client.py --bus ipc:///run/user/1000/stg/bus --out robot/ --count 20
    python tools/robot_client.py --bus tcp://robot-pc:7400 --out robot/ --duration 30 \\
        --width 320 --height 240 --request-every 1 --keys keys/ --key-name robot

The view asked for is the camera of the first image received, at --width x --height (a robot
would put its own camera here), as a standing (follow-live) view unless --one-shot. Exit codes:
0 received what was asked, 1 it did not (nothing arrived in --timeout), 2 bad usage.
"""

from __future__ import annotations

import argparse
import json
import signal
import struct
import sys
import threading
import time
import zlib
from pathlib import Path

import msgpack
import numpy as np
import zmq
import zmq.auth

# proto/envelope.yaml: lanes in order (latest, reliable, bulk), each with an in and an out side.
LANES = ("latest", "reliable", "bulk")
IMAGE_TOPIC, VIEW_TOPIC = "avatar/image", "avatar/view"
IMAGE_LANE, VIEW_LANE = "latest", "reliable"
DTYPES = {"uint8": "u1", "float32": "<f4", "float64": "<f8"}


def endpoint(url: str, lane: str, side: str) -> str:
    scheme, _, rest = url.partition("://")
    if scheme == "tcp":
        host, _, port = rest.rpartition(":")
        return f"tcp://{host}:{int(port) + 2 * LANES.index(lane) + (0 if side == 'in' else 1)}"
    if scheme in ("ipc", "inproc"):
        return f"{url}.{lane}.{side}"
    raise SystemExit(f"robot_client: bus URL {url!r} must be ipc://PATH or tcp://HOST:PORT")


def topic(namespace: str, name: str) -> str:
    return f"{namespace.strip('/')}/{name}" if namespace.strip("/") else name


def write_png(path: Path, rgb: np.ndarray) -> None:
    """An 8-bit RGB PNG, with zlib only."""
    h, w, _ = rgb.shape
    raw = b"".join(b"\x00" + rgb[y].tobytes() for y in range(h))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(raw, 6))
        + chunk(b"IEND", b"")
    )


def decode_image(frames: list, want_topic: bytes) -> dict | None:
    """A RenderedImage as {fields..., arrays}; None for anything malformed (counted by the caller)."""
    if len(frames) < 2 or frames[0].bytes != want_topic:
        return None
    try:
        header = msgpack.unpackb(frames[1].buffer, raw=False)
    except Exception:
        return None
    if not isinstance(header, dict) or header.get("type") != "RenderedImage" or header.get("v") != 1:
        return None
    descriptors = header.get("arrays", [])
    if not isinstance(descriptors, list) or len(descriptors) != len(frames) - 2:
        return None
    arrays = {}
    for desc, frame in zip(descriptors, frames[2:], strict=True):
        dtype = DTYPES.get(desc.get("dtype"))
        shape = desc.get("shape")
        if dtype is None or not isinstance(shape, list):
            return None
        dt = np.dtype(dtype)
        if frame.buffer.nbytes != int(np.prod(shape)) * dt.itemsize:
            return None
        arrays[desc["name"]] = np.frombuffer(frame.buffer, dtype=dt).reshape(shape)
    image = arrays.get("image")
    if image is None or image.ndim != 3 or image.shape[2] != 3:
        return None
    header["arrays"] = arrays
    return header


class LatestReader:
    """Reads the image socket continuously in a thread and keeps only the newest image (keep-last)."""

    def __init__(self, sock: zmq.Socket, want_topic: bytes):
        self.sock = sock
        self.want = want_topic
        self.lock = threading.Condition()
        self.latest = None
        self.received = 0
        self.malformed = 0
        self.stop = False
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def run(self) -> None:
        while not self.stop:
            if not self.sock.poll(100):
                continue
            frames = self.sock.recv_multipart(copy=False)
            if len(frames) == 1 and len(frames[0]) == 0:
                continue  # the broker's no-op
            msg = decode_image(frames, self.want)
            with self.lock:
                if msg is None:
                    self.malformed += 1
                    continue
                self.received += 1
                self.latest = msg
                self.lock.notify()

    def take(self, timeout: float):
        with self.lock:
            if self.latest is None:
                self.lock.wait(timeout)
            msg, self.latest = self.latest, None
            return msg


def view_request(seq: int, source: dict, width: int, height: int, follow_live: bool, src: str) -> list:
    """[topic, header, K, R, t] of a ViewRequest for ``source``'s camera at width x height."""
    arrays = source["arrays"]
    h, w = arrays["image"].shape[:2]
    K = np.array(arrays["K"], np.float64)
    K[0] *= width / w
    K[1] *= height / h
    header = {
        "type": "ViewRequest",
        "v": 1,
        "seq": seq,
        "stamp_ns": time.time_ns(),
        "src": src,
        "request_id": seq + 1,
        "width": width,
        "height": height,
        "follow_live": follow_live,
        "arrays": [
            {"name": n, "dtype": "float64", "shape": list(s)}
            for n, s in (("K", (3, 3)), ("R", (3, 3)), ("t", (3,)))
        ],
    }
    R = np.ascontiguousarray(arrays["R"], np.float64)
    t = np.ascontiguousarray(arrays["t"], np.float64)
    return [header, np.ascontiguousarray(K), R, t]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n")[0],
        epilog=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--bus", required=True, help="bus URL (ipc://PATH or tcp://HOST:PORT)")
    parser.add_argument("--namespace", default="", help="topic namespace")
    parser.add_argument("--out", type=Path, required=True, help="folder for the images and images.jsonl")
    parser.add_argument("--count", type=int, default=10, help="stop after this many images (0: no limit)")
    parser.add_argument(
        "--duration", type=float, default=0.0, help="stop after this many seconds (0: no limit)"
    )
    parser.add_argument("--timeout", type=float, default=30.0, help="give up when nothing arrives this long")
    parser.add_argument("--width", type=int, default=0, help="width of the view to ask for (0: ask for none)")
    parser.add_argument("--height", type=int, default=0, help="height of the view to ask for")
    parser.add_argument("--one-shot", action="store_true", help="ask for single renders, not a standing view")
    parser.add_argument("--request-every", type=float, default=1.0, help="seconds between view requests")
    parser.add_argument("--src", default="robot", help="our name in the requests")
    parser.add_argument("--keys", type=Path, help="CURVE key folder (tcp with stg-keys)")
    parser.add_argument("--key-name", help="our key name in KEYS/clients")
    args = parser.parse_args(argv)
    if args.count < 0 or args.duration < 0 or (args.width > 0) != (args.height > 0):
        print(
            "robot_client: --count/--duration must be >= 0; give both --width and --height", file=sys.stderr
        )
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    # Our own handlers: started in the background, a process inherits SIGINT ignored.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.default_int_handler)

    ctx = zmq.Context()
    sub = ctx.socket(zmq.SUB)
    pub = ctx.socket(zmq.PUB)
    for sock in (sub, pub):
        sock.linger = 0
        if args.keys:
            public, secret = zmq.auth.load_certificate(
                str(args.keys / "clients" / f"{args.key_name}.key_secret")
            )
            server, _ = zmq.auth.load_certificate(str(args.keys / "server.key"))
            sock.curve_secretkey, sock.curve_publickey, sock.curve_serverkey = secret, public, server
    sub.rcvhwm = 4
    image_topic = topic(args.namespace, IMAGE_TOPIC).encode()
    sub.connect(endpoint(args.bus, IMAGE_LANE, "out"))
    sub.subscribe(image_topic)
    pub.connect(endpoint(args.bus, VIEW_LANE, "in"))
    reader = LatestReader(sub, image_topic)

    saved = 0
    requests = 0
    last_request = 0.0
    start = last_seen = time.monotonic()
    log = (args.out / "images.jsonl").open("w")
    try:
        while True:
            msg = reader.take(timeout=min(1.0, args.timeout))
            now = time.monotonic()
            if msg is None:
                if now - last_seen > args.timeout:
                    print(
                        f"robot_client: nothing on {image_topic.decode()} for {args.timeout:g} s",
                        file=sys.stderr,
                    )
                    return 1
                continue
            last_seen = now
            arrays = msg.pop("arrays")
            saved += 1
            write_png(args.out / f"{saved:05d}.png", np.ascontiguousarray(arrays["image"]))
            msg.update(
                file=f"{saved:05d}.png",
                shape=list(arrays["image"].shape),
                received_latency_ms=(time.time_ns() - msg.get("source_stamp_ns", 0)) / 1e6,
            )
            log.write(json.dumps(msg) + "\n")
            log.flush()
            if args.width and now - last_request >= args.request_every:
                frames = view_request(
                    requests, {"arrays": arrays}, args.width, args.height, not args.one_shot, args.src
                )
                header = frames[0]
                pub.send_multipart(
                    [topic(args.namespace, VIEW_TOPIC).encode(), msgpack.packb(header), *frames[1:]]
                )
                requests += 1
                last_request = now
            if (args.count and saved >= args.count) or (args.duration and now - start >= args.duration):
                break
    except KeyboardInterrupt:
        pass
    finally:
        log.close()
        reader.stop = True
        reader.thread.join(1.0)
        sub.close()
        pub.close()
        ctx.term()
    print(
        f"robot_client: saved {saved} images to {args.out} "
        f"({requests} view requests, {reader.malformed} malformed)"
    )
    return 0 if saved and (not args.count or saved >= args.count) else 1


if __name__ == "__main__":
    sys.exit(main())
