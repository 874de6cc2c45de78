"""stg-train / stg-eval / stg-render / stg-export end to end on a tiny capture, their exit codes, and a
kill -9 in the middle of stg-train followed by --resume."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from stg_node.avatar.data_spec import DataSpec
from stg_node.cli import evaluate as eval_cli
from stg_node.cli import export as export_cli
from stg_node.cli import render as render_cli
from stg_node.cli import train as train_cli

ROOT = Path(__file__).resolve().parents[2]
TRAIN_ARGS = ["--format", "synthetic", "--preset", "fast", "--size", "128", "--no-progress"]


@pytest.fixture(scope="module")
def run_dir(tiny_synth, tmp_path_factory):
    out = tmp_path_factory.mktemp("runs") / "run"
    code = train_cli.main(["--data", str(tiny_synth), "--out", str(out), "--iters", "12", *TRAIN_ARGS])
    assert code == 0
    return out


def test_train_writes_a_complete_run_folder(run_dir, capsys):
    for name in (
        "config.json",
        "checkpoint.stgsnap",
        "avatar.stgsnap",
        "summary.json",
        "train_log.jsonl",
        "training_curves.png",
    ):
        assert (run_dir / name).is_file(), name
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["finished"] and summary["iterations"] == 12 and summary["gaussians"] > 0
    config = json.loads((run_dir / "config.json").read_text())
    assert config["data"]["format"] == "synthetic" and config["config"]["preset"] == "fast"


def test_eval_json_is_the_last_line_with_the_contract_keys(run_dir, capsys, tiny_synth):
    assert (
        eval_cli.main([str(run_dir), "--split", "novel_view", "--json", "--no-progress", "--lpips", "none"])
        == 0
    )
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in (
        "psnr",
        "ssim",
        "lpips",
        "images",
        "gaussians",
        "active_motion_fraction",
        "model_mb",
        "train_seconds",
    ):
        assert key in result, key
    assert result["images"] == 2 * 3  # 2 held-out cameras x frames 0, 4, 8
    assert 5.0 < result["psnr"] < 60.0
    # novel poses: the held-out frames (12 rendered, 10 trained on), every camera of the split
    assert (
        eval_cli.main([str(run_dir), "--split", "novel_pose", "--json", "--no-progress", "--lpips", "none"])
        == 0
    )
    novel = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    views = DataSpec(str(tiny_synth), "synthetic", size=128).open("novel_pose")
    assert novel["images"] == len(views) > 0 and {s.index for s in views} <= {10, 11}
    assert 5.0 < novel["psnr"] < 60.0 and 0.0 < novel["ssim"] <= 1.0


def test_eval_both_splits_reports_the_gap_body_parts_and_the_condition(run_dir, capsys):
    assert eval_cli.main([str(run_dir), "--split", "both", "--json", "--no-progress", "--lpips", "none"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    nv, np_ = result["novel_view"], result["novel_pose"]
    assert result["gap_db"] == pytest.approx(nv["psnr"] - np_["psnr"])
    assert set(nv["parts"]) == {"head", "torso", "arms", "hands", "legs", "feet"}
    assert all(5.0 < v < 80.0 for v in nv["parts"].values() if v == v)
    # The parts pool the same pixels as the whole image's body: the whole-image PSNR (body plus the
    # background, which the avatar gets nearly right) is above the worst part's.
    assert nv["psnr"] > min(v for v in nv["parts"].values() if v == v)
    assert result["condition"]["shading"] == "lambert" and result["condition"]["motion"] == "dance"
    assert result["condition"]["held_out"]["frames"] == 1  # frame 10: every 4th after the 10 training frames
    assert eval_cli.main([str(run_dir), "--split", "novel_pose", "--no-progress", "--lpips", "none"]) == 0
    text = capsys.readouterr().out
    assert "per body part" in text and "benchmark: lambert light, trained on dance" in text


def test_render_under_a_given_light_learned_baked_and_albedo(run_dir, tmp_path):
    """--light: a red light from the camera's side reddens the avatar; baked and albedo render; a bad
    value is a usage error."""
    from stg_node.avatar.shading import directional_irradiance

    red = directional_irradiance([[0.0, -1.0, 0.3]], [[1.2, 0.2, 0.2]], ambient=[0.1, 0.1, 0.1])
    means = {}
    for name, light in (
        ("learned", "learned"),
        ("baked", "baked"),
        ("albedo", "albedo"),
        ("red", ",".join(f"{v:.6f}" for v in red.reshape(-1).tolist())),
    ):
        out = tmp_path / name
        args = [str(run_dir), "-o", str(out), "--views", "dataset", "--frames", "1", "--light", light]
        assert render_cli.main([*args, "--no-progress"]) == 0, name
        image = cv2.cvtColor(cv2.imread(str(out / "000000.png")), cv2.COLOR_BGR2RGB).astype(float)
        body = image.sum(-1) > 0
        means[name] = image[body].mean(0)
    red_ratio = means["red"][0] / means["red"][2]
    assert red_ratio > 1.5 * means["learned"][0] / means["learned"][2]
    assert render_cli.main([str(run_dir), "-o", str(tmp_path / "bad"), "--light", "disco"]) == 2


def test_render_orbit_to_mp4_and_a_pose_file_to_pngs(run_dir, tmp_path, tiny_synth):
    video = tmp_path / "orbit.mp4"
    assert render_cli.main([str(run_dir), "-o", str(video), "--frames", "3", "--no-progress"]) == 0
    cap = cv2.VideoCapture(str(video))
    frames = 0
    while cap.read()[0]:
        frames += 1
    assert frames == 3
    # Animation from a pose file: 2 poses, the avatar's own shape.
    poses = np.zeros((2, 72), np.float32)
    poses[1, 3 * 16 + 2] = -1.0  # raise an arm
    pose_file = tmp_path / "poses.npz"
    np.savez(
        pose_file,
        poses=poses,
        Rh=np.array([[np.pi / 2, 0, 0]] * 2, np.float32),
        Th=np.zeros((2, 3), np.float32),
        shapes=np.zeros((2, 10), np.float32),
    )
    out = tmp_path / "anim"
    assert render_cli.main([str(run_dir), "-o", str(out), "--poses", str(pose_file), "--no-progress"]) == 0
    images = sorted(out.glob("*.png"))
    assert len(images) == 2
    a, b = (cv2.imread(str(p)) for p in images)
    assert a.shape == (128, 128, 3) and a.any() and not np.array_equal(a, b)


def test_default_renders_frame_the_avatar_whole_and_two_thirds_tall(run_dir, tmp_path):
    """Orbit and follow renders: the avatar never touches the border and is about 2/3 of the height
    (measured on the rendered alpha), also at another output size and fill."""
    from stg_node.avatar.animation import render_run
    from stg_node.avatar.framing import FramingRule

    for views in ("orbit", "follow"):
        summary = render_run(run_dir, tmp_path / f"{views}.mp4", views=views, frames=8, show_progress=False)
        framing = summary.framing
        assert summary.frames == framing.frames == 8
        assert framing.whole == 1.0, views
        assert 0.55 < framing.median_height < 0.8, (views, framing)
    summary = render_run(
        run_dir, tmp_path / "half", frames=4, size=96, rule=FramingRule(fraction=0.4), show_progress=False
    )
    assert summary.framing.whole == 1.0
    assert 0.3 < summary.framing.median_height < 0.5


def test_export_canonical_and_posed_ply(run_dir, tmp_path):
    from stg_node.splat.ply import load_ply

    assert export_cli.main([str(run_dir), "-o", str(tmp_path / "c.ply")]) == 0
    assert export_cli.main([str(run_dir), "-o", str(tmp_path / "f.ply"), "--frame", "3"]) == 0
    canonical, posed = load_ply(tmp_path / "c.ply"), load_ply(tmp_path / "f.ply")
    summary = json.loads((run_dir / "summary.json").read_text())
    assert canonical.means.shape[0] == summary["gaussians"]
    assert 0 < posed.means.shape[0] <= summary["gaussians"]
    assert not np.allclose(canonical.means[:10], posed.means[:10])
    assert export_cli.main([str(run_dir), "-o", str(tmp_path / "x.ply"), "--frame", "999"]) == 2


def test_exit_codes(tiny_synth, tmp_path):
    data = ["--data", str(tiny_synth), "--out", str(tmp_path / "r")]
    assert train_cli.main([*data, "--train-frames", "5:2", *TRAIN_ARGS]) == 2
    assert train_cli.main([*data, "--iters", "0", *TRAIN_ARGS]) == 2
    assert train_cli.main([*data, "--format", "nope"]) == 2
    assert (
        train_cli.main(["--data", str(tmp_path / "missing"), "--out", str(tmp_path / "r2"), *TRAIN_ARGS]) == 1
    )
    # A synthetic range past the generator's training frames is bad data, said clearly.
    assert train_cli.main([*data, "--train-frames", "0:50", "--iters", "1", *TRAIN_ARGS]) == 1
    assert eval_cli.main([str(tmp_path), "--split", "novel_view"]) == 1  # not a run folder
    assert render_cli.main([str(tmp_path), "-o", str(tmp_path / "x.gif")]) == 2


def _wait_for(path: Path, predicate, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if path.is_file():
            try:
                if predicate():
                    return
            except Exception:
                pass
        time.sleep(0.05)
    raise AssertionError(f"{path} not ready within {timeout} s")


def test_kill_9_then_resume_gives_the_uninterrupted_result(tiny_synth, tmp_path):
    """stg-train is SIGKILLed after its first checkpoint; --resume finishes the run, and the final model
    equals that of a run that was never interrupted (same seed, data, backend, one thread)."""
    from stg_node.avatar.snapshot import read_snapshot_file

    common = [
        "--data",
        str(tiny_synth),
        *TRAIN_ARGS,
        "--iters",
        "40",  # a kill after the first checkpoint has 30 steps to land in
        "--checkpoint-every",
        "10",
        "--seed",
        "3",
    ]
    env = {**os.environ, "STG_THREADS": "1", "PYTHONPATH": str(ROOT)}
    killed = tmp_path / "killed"
    proc = subprocess.Popen(
        [sys.executable, "-m", "stg_node.cli.train", "--out", str(killed), *common],
        cwd=ROOT,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        checkpoint = killed / "checkpoint.stgsnap"
        _wait_for(checkpoint, lambda: read_snapshot_file(checkpoint).iteration >= 10, timeout=300)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    at_kill = read_snapshot_file(killed / "checkpoint.stgsnap").iteration
    assert 10 <= at_kill < 40
    assert train_cli.main(["--out", str(killed), *common, "--resume"]) == 0
    assert train_cli.main(["--out", str(tmp_path / "straight"), *common]) == 0
    a = read_snapshot_file(killed / "avatar.stgsnap")
    b = read_snapshot_file(tmp_path / "straight" / "avatar.stgsnap")
    assert a.iteration == b.iteration == 40
    assert set(a.arrays) == set(b.arrays)
    for name in a.arrays:
        assert np.array_equal(a.arrays[name], b.arrays[name]), name
