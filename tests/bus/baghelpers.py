"""Helpers for the stg-bag tests: encoded messages as raw bytes, and an independent MCAP read."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from bushelpers import sample_messages
from mcap.reader import make_reader

from stg_node.bus import encode

ROOT = Path(__file__).resolve().parents[2]


def raw_frames(frames) -> list[bytes]:
    """Any [topic, header, *buffers] (numpy arrays, zmq frames, memoryviews) as a list of bytes."""
    return [bytes(memoryview(f).cast("B")) if not isinstance(f, bytes) else f for f in frames]


def encoded_stream(count: int, *, seed: int = 0, src: str = "talker", start_ns: int = 10**18, step_ns=10**7):
    """``count`` rounds of every message type, encoded as the bus would send them:
    [(log_time_ns, [topic, header, *buffers] as bytes)] in send order."""
    samples = sample_messages(seed)
    out = []
    seqs: dict[str, int] = {}
    t = start_ns
    for _ in range(count):
        for msg in samples.values():
            topic = msg.SPEC.topic
            seq = seqs.get(topic, 0)
            seqs[topic] = seq + 1
            frames = encode(msg, topic=topic, seq=seq, src=src, stamp_ns=t - 1000)
            out.append((t, raw_frames(frames)))
            t += step_ns
    return out


def mcap_messages(path) -> list[tuple[str, object, object]]:
    """(topic, channel, message) of every message, read by the mcap package alone, in log-time order."""
    with open(path, "rb") as f:
        return [(channel.topic, channel, message) for _s, channel, message in make_reader(f).iter_messages()]


def wait_written(recorder, count: int, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while recorder.stats().written < count and time.monotonic() < deadline:
        recorder.poll(0.05)
    assert recorder.stats().written >= count, recorder.stats()


def image_frames(count: int, h: int = 48, w: int = 64, seed: int = 0) -> list[np.ndarray]:
    """Smooth, distinct RGB images (video codecs keep them close), one per index."""
    yy, xx = np.mgrid[0:h, 0:w]
    images = []
    for i in range(count):
        r = (xx * 4 + i * 9) % 256
        g = (yy * 5 + i * 3) % 256
        b = ((xx + yy) * 2 + seed) % 256
        images.append(np.stack([r, g, b], axis=-1).astype(np.uint8))
    return images
