"""launch/demo.yaml with the real avatar, watched by tools/robot_client.py (a robot stack's view),
and recorded by its recorder node (record:=FILE), read back with the mcap package."""

from __future__ import annotations

import json

import pytest
from mcap.reader import make_reader
from nodehelpers import ROOT, run_launch


@pytest.mark.slow
def test_the_demo_trains_renders_serves_a_robot_and_ends_with_a_summary(tmp_path):
    out, robot, recording = tmp_path / "demo", tmp_path / "robot", tmp_path / "demo.mcap"
    url = f"ipc://{tmp_path}/bus"
    run = run_launch(
        [str(ROOT / "launch" / "demo.yaml"), f"out:={out}", f"bus:={url}", "frames:=20", "size:=96",
         "iters:=150", f"record:={recording}"],
        timeout=600,  # the demo ends on its own
        client_args=["--bus", url, "--out", str(robot), "--count", "8", "--width", "64", "--height", "48",
                     "--timeout", "240"],
    )  # fmt: skip
    assert run.client_code == 0, run.client_output + run.log[-3000:]
    log = run.log
    assert run.code == 0, log[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["iterations"] == 150 and summary["finished"] and summary["num_gaussians"] > 0
    assert summary["psnr"] > 12.0  # a 20-frame subject after 150 steps; far above a blank image
    assert (out / "avatar.mp4").stat().st_size > 0 and (out / "avatar_sheet.png").is_file()
    records = [json.loads(line) for line in (robot / "images.jsonl").read_text().splitlines()]
    assert len(records) == 8 and all(r["snapshot_version"] >= 1 for r in records)
    assert any(r["request_id"] >= 1 and r["shape"] == [48, 64, 3] for r in records)  # the view it asked for
    assert "summary:" in log
    with open(recording, "rb") as f:  # the whole session, finished cleanly when the launch ended
        reader = make_reader(f)
        topics = {channel.topic for _s, channel, _m in reader.iter_messages()}
        metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    assert {"camera/frame", "body/pose", "trainer/metrics", "avatar/snapshot", "avatar/image"} <= topics
    assert metadata["stg.launch"]["text"] == (ROOT / "launch" / "demo.yaml").read_text()
    assert metadata["stg.recording.end"]["clean"] == "true"
