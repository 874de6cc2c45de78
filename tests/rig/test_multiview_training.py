"""Multi-view training: stg-synth cameras that render every frame, the splits of several training
cameras (every format), frames of interleaved cameras keeping their own optical flow, and
stg-train --train-cameras end to end on a tiny capture."""

from __future__ import annotations

import json

import numpy as np
import pytest

from stg_node.avatar.data_spec import DataSpec
from stg_node.avatar.frames import FrameStore, TrainFrame
from stg_node.cli import evaluate as eval_cli
from stg_node.cli import render as render_cli
from stg_node.cli import train as train_cli
from stg_node.data.errors import DatasetError
from stg_node.data.splits import FrameRange, RigProtocol
from stg_node.data.synth.generate import SynthConfig, generate


@pytest.fixture(scope="module")
def ring(tmp_path_factory):
    """6 cameras, 3 of them (1, 3, 5) rendering every frame; 15 frames at 96 px (12 train)."""
    out = tmp_path_factory.mktemp("mv") / "ring"
    generate(
        SynthConfig(
            out=out,
            num_frames=15,
            size=96,
            num_novel_views=5,
            view_every=4,
            supersample=1,
            train_cameras=(0, 2, 4),
        ),
        progress=False,
    )
    return out


def test_stg_synth_renders_its_training_cameras_on_every_frame(ring):
    meta = json.loads((ring / "synth.json").read_text())
    assert [c["role"] for c in meta["cameras"]] == ["train", "novel_view"] * 3
    assert meta["rendered"]["Camera_B3"] == list(range(15))
    assert meta["rendered"]["Camera_B2"] == [0, 4, 8, 12]
    assert meta["splits"]["train"] == [{"cameras": [0, 2, 4], "frames": list(range(12))}]
    assert meta["splits"]["novel_view"][0]["cameras"] == [1, 3, 5]
    assert (ring / "Camera_B5" / "000013.png").is_file() and not (ring / "Camera_B4" / "000013.png").exists()


def test_stg_synth_refuses_a_camera_the_ring_does_not_have(tmp_path):
    with pytest.raises(ValueError, match=r"--train-cameras \[9\]: the rig has cameras 1-3"):
        SynthConfig(out=tmp_path, num_novel_views=2, train_cameras=(0, 8)).validate()


def test_several_training_cameras_split_the_synthetic_capture(ring):
    default = DataSpec(str(ring), "synthetic", size=96)  # the generator's training cameras
    assert default.open("train").camera_names == ["1", "3", "5"]
    two = DataSpec(str(ring), "synthetic", size=96, train_cameras=("1", "5"))
    train, novel = two.open("train"), two.open("novel_view")
    assert train.camera_names == ["1", "5"] and len(train) == 2 * 12
    assert novel.camera_names == ["2", "3", "4", "6"] and novel.frames == [0, 4, 8]
    assert set(two.open("novel_pose").camera_names) == {"1", "2", "3", "4", "5", "6"}
    mono = DataSpec(str(ring), "synthetic", size=96, train_camera="3")
    assert mono.open("train").camera_names == ["3"]
    with pytest.raises(DatasetError, match="camera 2 was rendered on every 4th frame only"):
        DataSpec(str(ring), "synthetic", size=96, train_cameras=("1", "2")).open("train")


def test_the_spec_round_trips_and_refuses_both_camera_options(ring):
    spec = DataSpec(str(ring), "synthetic", (0, 8), None, 96, ("1", "5"))
    back = DataSpec.from_dict(json.loads(json.dumps(spec.to_dict())))
    assert back == spec and back.rig
    assert DataSpec.from_dict({"root": "x", "format": "zju"}).train_cameras is None  # old run folders
    with pytest.raises(ValueError, match="not both"):
        DataSpec(str(ring), "synthetic", train_camera="1", train_cameras=("1", "3"))
    with pytest.raises(ValueError, match="distinct"):
        DataSpec(str(ring), "synthetic", train_cameras=("1", "1"))


def test_rig_protocol_holds_out_every_other_camera():
    protocol = RigProtocol(("1", "7"), FrameRange(0, 100))
    assert protocol.split("train").cameras == ("1", "7")
    novel = protocol.split("novel_view")
    assert novel.exclude == ("1", "7") and novel.frames == FrameRange(0, 100, 30)
    cams, frames = novel.resolve([str(i) for i in range(1, 24)], 300)
    assert len(cams) == 21 and frames == [0, 30, 60, 90]
    with pytest.raises(DatasetError, match="every camera trains"):
        novel.resolve(["1", "7"], 300)
    assert protocol.split("novel_pose").frames == FrameRange(100, None, 30)


def test_the_folder_format_trains_on_several_cameras(ring, tmp_path):
    """The same capture rewritten in the folder format: --train-cameras works there too."""
    import shutil

    from stg_node.data.synth.dataset import open_synth

    root = tmp_path / "capture"
    cameras, poses = {}, []
    source = open_synth(ring, "train", size=None)
    for name in ("1", "3", "5"):
        cam = source.camera(name)
        cameras[name] = {
            "K": cam.K.tolist(),
            "R": cam.R.tolist(),
            "t": cam.t.tolist(),
            "width": 96,
            "height": 96,
        }
        for folder in ("images", "masks"):
            (root / folder / name).mkdir(parents=True)
        for frame in source.frames:
            shutil.copy(source.image_path(frame, name), root / "images" / name / f"{frame:06d}.png")
            shutil.copy(source.mask_path(frame, name), root / "masks" / name / f"{frame:06d}.png")
    for frame in source.frames:
        smpl = source.smpl(frame)
        poses.append((smpl.poses.reshape(72), smpl.Rh, smpl.Th, smpl.betas))
    (root / "cameras.json").write_text(json.dumps({"fps": 30, "cameras": cameras}))
    np.savez(
        root / "poses.npz",
        poses=np.stack([p[0] for p in poses]),
        Rh=np.stack([p[1] for p in poses]),
        Th=np.stack([p[2] for p in poses]),
        betas=np.stack([p[3] for p in poses]),
    )
    spec = DataSpec(str(root), "folder", size=96, train_cameras=("1", "5"))
    assert spec.open("train").camera_names == ["1", "5"]
    assert spec.open("novel_view").camera_names == ["3"]
    assert len(spec.open("novel_view")) == 1  # frame 0 (every 30th of 12)


def test_interleaved_cameras_each_keep_their_own_flow(ring):
    spec = DataSpec(str(ring), "synthetic", size=96, train_cameras=("1", "3"))
    store = FrameStore(flow=True)
    for sample in spec.open("train"):  # frame-major: camera 1, camera 3, camera 1, ...
        store.add(TrainFrame.from_sample(sample))
    with_flow = [s for s in store.frames if s.flow is not None]
    assert len(with_flow) == 2 * 11  # every frame but each camera's last
    for stored in with_flow:
        assert stored.next_time > stored.frame.time
    by_camera = {s.frame.camera.name for s in with_flow}
    assert by_camera == {"1", "3"}


def test_each_training_camera_keeps_its_own_missed_flow_column(ring):
    """The trainer numbers its cameras in order of arrival and hands each step's to the densifier:
    after steps that render their motion, the missed-flow statistic has one column per camera, each
    filled only by its own camera's steps, and R_i is the most any of them sees (densify.py)."""
    import torch

    from stg_node.avatar import Trainer, preset

    config = preset("fast").replace(iterations=40, **{"loss.flow_every": 1})
    trainer = Trainer(config, seed=0)
    trainer.add_frames(DataSpec(str(ring), "synthetic", size=96, train_cameras=("1", "3", "5")).open("train"))
    assert trainer.camera_slots == {"1": 0, "3": 1, "5": 2}
    drawn = set()
    while trainer.iteration < 40:
        before = trainer.densify_state.get("resid_cam")
        before = None if before is None else before.clone()
        trainer.step()
        after = trainer.densify_state["resid_cam"] if "resid_cam" in trainer.densify_state else None
        if after is None or before is None or before.shape != after.shape:
            continue
        changed = {int(c) for c in (after != before).any(dim=0).nonzero().flatten()}
        assert len(changed) <= 1  # a step reads one camera's flow, into that camera's column only
        drawn |= changed
    state = trainer.densify_state
    assert state["resid_cam"].shape[1] == 3 and len(drawn) >= 2
    assert torch.equal(state["resid_w"], state["resid_cam"].amax(dim=1))


def test_a_resumed_rig_keeps_each_cameras_column_whatever_order_it_reconnects_in(ring, tmp_path):
    """The columns of the per-camera statistics are the checkpoint's: a rig whose cameras come
    back in another order (camera 5's frames first) must not hand camera 1's missed flow to
    camera 5. A camera the checkpoint never saw takes the next free column."""
    import torch

    from stg_node.avatar import Trainer, preset

    config = preset("fast").replace(iterations=40, **{"loss.flow_every": 1})
    trainer = Trainer(config, seed=0)
    trainer.add_frames(DataSpec(str(ring), "synthetic", size=96, train_cameras=("1", "5")).open("train"))
    for _ in range(12):
        trainer.step()
    path = trainer.save(tmp_path / "rig.ckpt")
    before = trainer.densify_state["resid_cam"].clone()

    resumed = Trainer.load(path)
    frames = list(DataSpec(str(ring), "synthetic", size=96, train_cameras=("1", "3", "5")).open("train"))
    resumed.add_frames(sorted(frames, key=lambda s: s.camera.name != "5"))  # camera 5 first
    assert resumed.camera_slots == {"1": 0, "5": 1, "3": 2}
    assert resumed.color_turns is None  # still a rig: every row's colour
    assert torch.equal(resumed.densify_state["resid_cam"], before)


@pytest.mark.parametrize("cameras, applied", [(("1",), True), (("1", "5"), False)])
def test_the_line_of_sight_prior_holds_only_a_single_cameras_motion(ring, cameras, applied):
    """loss.line_of_sight keeps motion off the training camera's rays, the depth one camera cannot
    see; with several cameras around the subject the others see it, so the term is not applied."""
    from stg_node.avatar import Trainer, preset

    config = preset("fast").replace(iterations=3, nonrigid="on", **{"loss.line_of_sight": 1.0})
    trainer = Trainer(config, seed=0)
    trainer.add_frames(DataSpec(str(ring), "synthetic", size=96, train_cameras=cameras).open("train"))
    trainer.step()
    trainer.model.table["motion_gate"].data[:] = 1.0  # every Gaussian may move: the motion terms exist
    result = trainer.step()
    assert ("line_of_sight" in result.losses) == applied


def test_stg_train_with_several_cameras_end_to_end(ring, tmp_path, capsys):
    out = tmp_path / "run"
    common = [
        "--data",
        str(ring),
        "--format",
        "synthetic",
        "--preset",
        "fast",
        "--size",
        "96",
        "--no-progress",
    ]
    assert train_cli.main([*common, "--out", str(out), "--iters", "8", "--train-cameras", "1,5"]) == 0
    config = json.loads((out / "config.json").read_text())
    assert config["data"]["train_cameras"] == ["1", "5"]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 24
    capsys.readouterr()
    assert (
        eval_cli.main([str(out), "--split", "novel_view", "--json", "--no-progress", "--lpips", "none"]) == 0
    )
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["images"] == 4 * 3  # cameras 2, 3, 4, 6 x frames 0, 4, 8
    assert (
        render_cli.main(
            [str(out), "-o", str(tmp_path / "views"), "--views", "dataset", "--frames", "2", "--no-progress"]
        )
        == 0
    )
    assert (
        train_cli.main(
            [*common, "--out", str(tmp_path / "x"), "--train-camera", "1", "--train-cameras", "1,5"]
        )
        == 2
    )
    assert "not both" in capsys.readouterr().err


def test_zju_mocap_trains_on_several_cameras(tmp_path):
    from fixtures.datasets import write_zju_original

    root = tmp_path / "CoreView_999"
    write_zju_original(root, num_frames=40, num_cams=4)
    spec = DataSpec(str(root), "zju", size=64, train_cameras=("1", "3"))
    train = spec.open("train")
    assert train.camera_names == ["1", "3"] and len(train) == 2 * 40
    novel = spec.open("novel_view")
    assert novel.camera_names == ["2", "4"] and novel.frames == [0, 30]
    ranged = DataSpec(str(root), "zju", (0, 20), None, 64, ("1", "3"))
    assert ranged.open("train").frames == list(range(20)) and ranged.open("novel_pose").frames == [20]
    with pytest.raises(DatasetError, match=r"needs camera\(s\) \['9'\]"):
        DataSpec(str(root), "zju", size=64, train_cameras=("1", "9")).open("train")
