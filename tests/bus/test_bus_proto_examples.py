"""proto/README.md's raw pyzmq examples work against a live bus and import nothing of ours."""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from bushelpers import sample_messages

from stg_node.bus import Broker, BusConfig, Publisher, Subscriber, ViewRequest

README = Path(__file__).resolve().parents[2] / "proto" / "README.md"
ALLOWED_IMPORTS = {"sys", "time", "msgpack", "numpy", "zmq"}

# Runs an example as __main__, then fails if anything of ours got imported.
RUNNER = """
import runpy, sys
path = sys.argv[1]
sys.argv = sys.argv[1:]
runpy.run_path(path, run_name="__main__")
ours = sorted(m for m in sys.modules if m == "stg_node" or m.startswith("stg_node."))
assert not ours, f"the example imported {ours}"
"""


def _example(name: str) -> str:
    text = README.read_text()
    match = re.search(rf"<!-- example: {name} -->\s*```python\n(.+?)\n```", text, re.S)
    assert match, f"proto/README.md has no '{name}' example"
    return match.group(1)


def _imports(code: str) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(code)):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            names.add(node.module.split(".")[0])
    return names


@pytest.mark.parametrize("name", ["decode", "publish"])
def test_examples_import_only_zmq_msgpack_numpy(name):
    assert _imports(_example(name)) <= ALLOWED_IMPORTS


def _run(tmp_path: Path, name: str, *args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    script = tmp_path / f"{name}.py"
    script.write_text(_example(name))
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    return subprocess.run(
        [sys.executable, "-c", RUNNER, str(script), *args],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def test_decode_example_reads_our_rendered_images(tmp_path, ipc_url):
    with Broker(ipc_url, status_period_s=0):
        config = BusConfig(url=ipc_url)
        stop = threading.Event()

        def keep_publishing():
            with Publisher(config, node="renderer-test") as pub:
                msg = sample_messages()["RenderedImage"]
                while not stop.is_set():
                    pub.publish(msg)
                    stop.wait(0.02)

        thread = threading.Thread(target=keep_publishing, daemon=True)
        thread.start()
        try:
            result = _run(tmp_path, "decode", config.endpoint("latest", "out"), "avatar/image", "3")
        finally:
            stop.set()
            thread.join(5)
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    assert len(lines) == 3
    for line in lines:
        assert line.startswith("RenderedImage v1 seq")
        assert "'image': 'uint8[6, 8, 3]'" in line and "'K': 'float64[3, 3]'" in line
        assert "'request_src': 'robot'" in line


def test_our_subscriber_reads_the_publish_example(tmp_path, ipc_url):
    with Broker(ipc_url, status_period_s=0):
        config = BusConfig(url=ipc_url)
        script = tmp_path / "publish.py"
        script.write_text(_example("publish"))
        with Subscriber(config, ["avatar/view"]) as sub:
            proc = subprocess.Popen(
                [sys.executable, "-c", RUNNER, str(script), config.endpoint("reliable", "in"), "5"],
                cwd=tmp_path,
                env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"},
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
            try:
                got = list(sub.messages(timeout=60.0, count=5))
            finally:
                out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert len(got) == 5
    assert all(isinstance(m, ViewRequest) for m in got)
    assert [m.request_id for m in got] == [0, 1, 2, 3, 4]
    assert got[0].header.src == "robot-example" and (got[0].width, got[0].height) == (640, 480)
    np.testing.assert_array_equal(got[0].t, [0.0, 0.0, 3.0])
    assert sub.traffic.drops == {}
