"""An avatar survives the bus message and the checkpoint file bit for bit; bad files say what is wrong."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from avatar_helpers import small_config

from stg_node.avatar.renderer import AvatarRenderer
from stg_node.avatar.snapshot import (
    FORMAT,
    SnapshotError,
    model_from_snapshot,
    read_snapshot_file,
    strip_training_state,
    write_snapshot_file,
)
from stg_node.avatar.trainer import Trainer


@pytest.fixture(scope="module")
def trained(tiny_frames):
    trainer = Trainer(small_config(iterations=30, lr_pose=1e-4), seed=1)
    trainer.add_frames(tiny_frames)
    for _ in range(30):
        trainer.step()
    return trainer


def test_published_snapshot_renders_exactly_like_the_trainer_model(trained, tiny_frames, tmp_path):
    msg = trained.snapshot()
    assert msg.format == FORMAT and msg.num_gaussians == trained.model.table.num
    assert not any(k.startswith("train.") for k in msg.arrays)
    path = write_snapshot_file(tmp_path / "a.stgsnap", msg)
    back = read_snapshot_file(path)
    frame = tiny_frames[3]
    direct = AvatarRenderer(trained.model).render(frame.camera, frame.smpl, frame.time)
    loaded = AvatarRenderer.from_snapshot(back).render(frame.camera, frame.smpl, frame.time)
    assert np.array_equal(direct.image, loaded.image) and np.array_equal(direct.alpha, loaded.alpha)
    # Novel poses: the time code comes from the index that travelled with the model.
    novel = AvatarRenderer.from_snapshot(back).render(frame.camera, frame.smpl, None)
    assert novel.time_u == pytest.approx(trained.model.time_axis(frame.time), abs=1e-6)


def test_snapshot_goes_through_the_bus_codec(trained, tiny_frames):
    """Encoded for the wire and decoded (as a renderer on another machine would): every array
    bit for bit, and the model it rebuilds renders exactly like the trainer's."""
    from stg_node.bus.codec import decode, encode

    msg = trained.snapshot()
    frames = encode(msg, topic="avatar/snapshot", seq=1, src="test", stamp_ns=1)
    back = decode([bytes(f) for f in frames])
    assert back.arrays.keys() == msg.arrays.keys() and back.meta == msg.meta
    for name, array in msg.arrays.items():
        assert back.arrays[name].dtype == array.dtype and np.array_equal(back.arrays[name], array), name
    frame = tiny_frames[5]
    direct = AvatarRenderer(trained.model).render(frame.camera, frame.smpl, frame.time)
    wired = AvatarRenderer(model_from_snapshot(back)).render(frame.camera, frame.smpl, frame.time)
    assert np.array_equal(direct.image, wired.image) and np.array_equal(direct.alpha, wired.alpha)


def test_checkpoint_strips_to_the_published_message(trained, tmp_path):
    path = trained.save(tmp_path / "ck.stgsnap")
    ck = read_snapshot_file(path)
    assert any(k.startswith("train.") for k in ck.arrays)
    stripped = strip_training_state(ck)
    assert not any(k.startswith("train.") for k in list(stripped.arrays) + list(stripped.meta))
    assert set(stripped.arrays) == set(trained.snapshot().arrays)


def test_bad_files_and_messages_give_clear_errors(trained, tmp_path):
    good = write_snapshot_file(tmp_path / "g.stgsnap", trained.snapshot())
    data = good.read_bytes()
    (tmp_path / "trunc.stgsnap").write_bytes(data[: len(data) // 2])
    with pytest.raises(SnapshotError, match="truncated"):
        read_snapshot_file(tmp_path / "trunc.stgsnap")
    (tmp_path / "junk.stgsnap").write_bytes(b"not a snapshot at all")
    with pytest.raises(SnapshotError, match="magic"):
        read_snapshot_file(tmp_path / "junk.stgsnap")
    with pytest.raises(SnapshotError, match="no such"):
        read_snapshot_file(tmp_path / "missing.stgsnap")
    msg = trained.snapshot()
    with pytest.raises(SnapshotError, match="format"):
        model_from_snapshot(dataclasses.replace(msg, format="other/1"))
    arrays = dict(msg.arrays)
    del arrays["g.means"]
    with pytest.raises(SnapshotError, match="means"):
        model_from_snapshot(dataclasses.replace(msg, arrays=arrays))
    with pytest.raises(ValueError, match="not a training checkpoint"):
        Trainer.load(good)


def test_an_interrupted_write_leaves_the_previous_file(trained, tmp_path, monkeypatch):
    import os

    path = write_snapshot_file(tmp_path / "ck.stgsnap", trained.snapshot())
    before = path.read_bytes()

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError):
        write_snapshot_file(path, trained.snapshot())
    assert path.read_bytes() == before


def test_points_are_the_gaussians_the_renderer_draws_where_it_draws_them(trained, tiny_frames):
    """AvatarRenderer.points (the foxglove node's point cloud): as many points as Gaussians reach
    the rasterizer, and those visible at all project onto the avatar's own silhouette in the render."""
    renderer = AvatarRenderer.from_snapshot(trained.snapshot())
    frame = tiny_frames[2]
    out = renderer.render(frame.camera, frame.smpl, frame.time)
    points = renderer.points(frame.smpl, frame.time, camera_center=-frame.camera.R.T @ frame.camera.t)
    n = len(points.positions)
    assert n == out.num_rendered and points.colors.shape == (n, 3) and points.alpha.shape == (n,)
    assert points.colors.dtype == np.uint8 and points.alpha.dtype == np.uint8
    cam = points.positions @ np.asarray(frame.camera.R).T + np.asarray(frame.camera.t)
    pix = cam @ np.asarray(frame.camera.K).T
    uv = np.floor(pix[:, :2] / pix[:, 2:]).astype(int)
    h, w = out.alpha.shape
    opaque = (points.alpha >= 8) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    assert opaque.sum() > 0.3 * n
    on_silhouette = out.alpha[uv[opaque, 1], uv[opaque, 0]] > 0
    assert on_silhouette.mean() > 0.95
