"""proto/recording.md's reader example (mcap + msgpack + numpy, nothing of ours) reads our recordings."""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
from pathlib import Path

from baghelpers import encoded_stream
from test_bus_proto_examples import RUNNER

from stg_node.bus.recording import BagWriter

SPEC = Path(__file__).resolve().parents[2] / "proto" / "recording.md"


def _example() -> str:
    match = re.search(r"<!-- example: read-recording -->\s*```python\n(.+?)\n```", SPEC.read_text(), re.S)
    assert match, "proto/recording.md has no 'read-recording' example"
    return match.group(1)


def test_example_imports_only_mcap_msgpack_numpy():
    names = set()
    for node in ast.walk(ast.parse(_example())):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            names.add(node.module.split(".")[0])
    assert names <= {"sys", "msgpack", "numpy", "mcap"}


def test_example_reads_every_message_with_its_arrays(tmp_path):
    stream = encoded_stream(2)
    with BagWriter(tmp_path / "s.mcap", compression="zstd") as bag:
        for log_time, frames in stream:
            bag.write_frames(frames, log_time)
    script = tmp_path / "read_recording.py"
    script.write_text(_example())
    result = subprocess.run(
        [sys.executable, "-c", RUNNER, str(script), str(tmp_path / "s.mcap")],
        cwd=tmp_path,
        env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    assert len(lines) == len(stream)
    assert lines[0].startswith("camera/frame Frame seq 0 src talker")
    assert "'image': 'uint8[6, 8, 3]'" in lines[0] and "'depth': 'float32[6, 8]'" in lines[0]
    snapshot = next(line for line in lines if line.startswith("avatar/snapshot GaussianSnapshot seq 1"))
    assert "'mlp.0.weight': 'float16[16, 8]'" in snapshot and "'model_version': 4" in snapshot
