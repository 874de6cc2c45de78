"""tools/pose_reach.py on an stg-synth-shaped folder whose true poses walk 0.1 rad a frame with one
limb flipped for three frames: the report names the two jumps (closed-form chords) and the reach
stays the walk's step."""

import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
import pytest

TOOL = Path(__file__).resolve().parents[1] / "tools" / "pose_reach.py"


def _tool():
    spec = importlib.util.spec_from_file_location("pose_reach", TOOL)
    module = importlib.util.module_from_spec(spec)
    sys.modules["pose_reach"] = module
    spec.loader.exec_module(module)
    return module


def _chord(delta: float) -> float:
    return 2 * math.sqrt(2) * abs(math.sin(delta / 2))


def test_the_report_names_the_jumps_and_keeps_the_walks_reach(tmp_path, capsys):
    tool = _tool()
    folder = tmp_path / "subject"
    (folder / "new_params").mkdir(parents=True)
    for i in range(20):
        poses = np.zeros((1, 72), np.float32)
        poses[0, 16 * 3 + 2] = 0.1 * i + (1.2 if 7 <= i < 10 else 0.0)  # left shoulder
        np.save(folder / "new_params" / f"{i}.npy", {"poses": poses})
    keys, times = tool.synth_index(folder, frames=None)
    report = tool.report(keys, times)
    assert report["reach"] == pytest.approx(_chord(0.1), rel=1e-5)
    assert report["largest_step"] == pytest.approx(_chord(1.3), rel=1e-5)
    assert report["jump"] == pytest.approx([_chord(1.3), _chord(1.1)], abs=1e-3)
    assert report["gap"] == [] and report["glitch"] == []
    assert tool.main([str(folder), "--frames", "7"]) == 0  # before the flip: nothing left out
    assert "left out: none" in capsys.readouterr().out
