"""tools/chaos.py on a small launch (the stand-in avatar): kills in turn with standby copies, a flood,
a stalled subscriber, the broker killed, the recording and the end; its report says what it saw.
(The full run, on launch/replay_zju.yaml with the real avatar: docs/BENCHMARKS.md, "Chaos".)"""

from __future__ import annotations

import json
import subprocess
import sys

from fixtures.datasets import write_zju_original
from nodehelpers import ROOT

FAKE = "tests.nodes.fake_avatar"


def test_a_short_chaos_run_meets_its_targets_and_reports_each_fault(tmp_path):
    data = tmp_path / "subject"
    write_zju_original(data, num_frames=6, num_cams=1)
    launch = tmp_path / "chaos.yaml"
    launch.write_text(
        f"""
args:
  bus: {{default: ""}}
  record: {{default: ""}}
env: {{STG_THREADS: "1"}}
bus: {{url: $(arg bus)}}
nodes:
  - {{name: recorder, kind: recorder, params: {{path: $(arg record)}}, if: $(nonempty $(arg record))}}
  - {{name: tracker, kind: tracker, params: {{path: {data}}}, respawn: true, respawn_delay: 0.2}}
  - name: trainer
    kind: trainer
    params: {{avatar: {FAKE}, preset: slow, snapshot_every_s: 1, checkpoint_every_s: 2,
              checkpoint_dir: {tmp_path}/ckpt}}
    respawn: true
    respawn_delay: 0.2
    standby: true
  - name: renderer
    kind: renderer
    params: {{avatar: {FAKE}, size: 48, idle_rate_hz: 10}}
    respawn: true
    respawn_delay: 0.2
    standby: true
  - name: ingest
    kind: ingest
    params: {{path: {data}, size: 48, rate_hz: 20, loop: true}}
    after: [tracker, trainer, recorder]
    respawn: true
    respawn_delay: 0.2
"""
    )
    report = tmp_path / "chaos.json"
    result = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "chaos.py"), str(launch), "--duration", "24", "--every", "12",
         "--kill", "trainer,renderer", "--flood-s", "2", "--slow-s", "3", "--broker-down", "2",
         "--work", str(tmp_path / "work"), "--json", str(report)],
        cwd=ROOT, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
    found = json.loads(report.read_text())
    assert [k["node"] for k in found["kills"]] == ["trainer", "renderer"]
    trainer, renderer = found["kills"]
    assert trainer["back_s"] is not None and trainer["resumed_at"] == trainer["checkpoint_iteration"] + 1
    assert renderer["image_back_s"] is not None and renderer["recording_messages"] > 0
    assert found["flood"]["junk_sent"] > 0 and not found["flood"]["nodes_restarted"]
    assert set(found["slow_subscriber"]["memory"]) >= {"broker", "trainer", "renderer"}
    assert found["broker"]["nodes_exited"] == [] and found["broker"]["avatar_back_s"] is not None
    assert found["orphans"] == [] and found["launch_exit_code"] == 0
    assert found["recording"]["state"] == "complete" and found["targets_met"]
