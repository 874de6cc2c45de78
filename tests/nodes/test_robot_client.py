"""tools/robot_client.py (raw pyzmq + msgpack) against a running renderer (fake avatar)."""

from __future__ import annotations

import ast
import json
import time
from pathlib import Path

import numpy as np
from nodehelpers import ROOT, NodeThread, spawn
from test_renderer_node import body_at, renderer, snapshot, train_frame, wait_subscribed

from stg_node.bus import Bus

CLIENT = ROOT / "tools" / "robot_client.py"


def read_png(path: Path) -> np.ndarray:
    """An 8-bit RGB PNG as written by the client, decoded independently of it (PIL)."""
    from PIL import Image

    return np.asarray(Image.open(path).convert("RGB"))


def test_the_client_imports_nothing_of_ours():
    tree = ast.parse(CLIENT.read_text())
    modules = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    modules |= {n.module.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
    assert "stg_node" not in modules and modules <= {
        "argparse",
        "json",
        "signal",
        "struct",
        "sys",
        "threading",
        "time",
        "zlib",
        "pathlib",
        "msgpack",
        "numpy",
        "zmq",
        "__future__",
    }


def test_the_client_receives_asks_for_a_view_and_saves_images(broker, bus_url, tmp_path):
    node = renderer(bus_url, idle_rate_hz=20, max_rate_hz=20)
    out = tmp_path / "robot"
    with NodeThread(node), Bus(bus_url, node="pipeline", heartbeat_s=0) as bus:
        wait_subscribed(bus, "avatar/snapshot", "body/pose", "camera/frame")
        bus.publish(snapshot(4, color=(0.0, 0.8, 0.2)))
        bus.publish(train_frame())
        client = spawn(
            [
                str(CLIENT),
                "--bus",
                bus_url,
                "--out",
                str(out),
                "--count",
                "15",
                "--width",
                "40",
                "--height",
                "30",
                "--request-every",
                "0.2",
                "--timeout",
                "60",
            ]
        )
        deadline = time.monotonic() + 120
        while client.poll() is None and time.monotonic() < deadline:
            bus.publish(body_at([0.0, 0.0, 0.0]), stamp_ns=time.time_ns())
            time.sleep(0.05)
        out_text, _ = client.communicate(timeout=30)
    assert client.returncode == 0, out_text
    records = [json.loads(line) for line in (out / "images.jsonl").read_text().splitlines()]
    assert len(records) == 15 and "saved 15 images" in out_text
    assert all(r["type"] == "RenderedImage" and r["snapshot_version"] == 4 for r in records)
    asked = [r for r in records if r["request_id"] >= 1]  # the standing view it asked for
    assert asked and all(r["shape"] == [30, 40, 3] and r["request_src"] == "robot" for r in asked)
    first = read_png(out / records[0]["file"])
    assert list(first.shape) == records[0]["shape"]
    np.testing.assert_array_equal(
        np.unique(first.reshape(-1, 3), axis=0)[-1], [0, 204, 51]
    )  # the avatar's colour


def test_the_client_says_when_nothing_comes(bus_url, tmp_path):
    client = spawn([str(CLIENT), "--bus", bus_url, "--out", str(tmp_path), "--timeout", "1"])
    out, _ = client.communicate(timeout=30)
    assert client.returncode == 1 and "nothing on avatar/image" in out
    bad = spawn([str(CLIENT), "--bus", bus_url, "--out", str(tmp_path), "--width", "10"])
    bad.communicate(timeout=30)
    assert bad.returncode == 2
