"""One code path drives every SMPL-format body with a pose sequence read from real-data formats."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch
from smpl_fixtures import random_smpl_arrays, smplx_oracle, write_smpl_pkl

from stg_node.body import (
    axis_angle_to_matrix,
    drive_body,
    load_body_model,
    load_smpl_params,
    save_smpl_params,
)
from stg_node.data.synth.motions import make_motion


def _walk(num_frames: int, seed: int, betas=None):
    """The project's motion generator (z-up ZJU-MoCap world), a walking sequence."""
    return make_motion("walk", num_frames, 30.0, np.random.default_rng(seed), betas=betas)


def _write_zju_new_params(folder, motion):
    """ZJU-MoCap's layout: new_params/{i}.npy, each a pickled dict of (1, N) float arrays."""
    folder.mkdir()
    for i in range(len(motion)):
        np.save(
            folder / f"{i}.npy",
            {
                "poses": motion.poses[i : i + 1].reshape(1, 72).astype(np.float32),
                "Rh": motion.Rh[i : i + 1].astype(np.float32),
                "Th": motion.Th[i : i + 1].astype(np.float32),
                "shapes": np.atleast_2d(motion.betas).astype(np.float32)[:1],
            },
        )


@pytest.fixture(scope="module")
def sequence_dir(tmp_path_factory):
    motion = _walk(24, seed=1, betas=np.linspace(-0.5, 0.5, 10))
    folder = tmp_path_factory.mktemp("zju") / "new_params"
    _write_zju_new_params(folder, motion)
    return folder, motion


def test_zju_new_params_round_trip(sequence_dir):
    folder, motion = sequence_dir
    loaded = load_smpl_params(folder)
    assert len(loaded) == 24 and loaded.poses.shape == (24, 24, 3) and loaded.betas.shape == (24, 10)
    assert np.array_equal(loaded.poses, motion.poses) and np.array_equal(loaded.Th, motion.Th)
    one = load_smpl_params(folder / "3.npy")
    assert np.array_equal(one.poses[0], motion.poses[3]) and np.array_equal(one.Rh[0], motion.Rh[3])
    frame = loaded[3]  # one frame of a sequence is the per-frame type the datasets deliver
    assert frame.poses.shape == (24, 3) and np.array_equal(frame.Th, motion.Th[3])
    # Frame order is numeric (10.npy after 9.npy), not lexical.
    assert np.array_equal(loaded.poses[10], motion.poses[10])


def test_same_code_path_drives_smpl_and_open_body(tmp_path, sequence_dir):
    folder, _ = sequence_dir
    motion = load_smpl_params(folder)
    arrays = random_smpl_arrays(seed=4, num_verts=400)
    write_smpl_pkl(tmp_path / "SMPL_NEUTRAL.pkl", arrays)
    smpl = load_body_model(tmp_path, dtype=torch.float64)
    open_body = load_body_model(None, dtype=torch.float64)
    outputs = {name: drive_body(model, motion) for name, model in (("smpl", smpl), ("open", open_body))}

    # SMPL: the oracle (smplx) posed with the same frames, placed with Rh/Th as ZJU defines them.
    oracle = smplx_oracle(arrays, torch.float64)
    poses = torch.as_tensor(motion.poses, dtype=torch.float64)
    ref = oracle(
        betas=torch.as_tensor(motion.betas, dtype=torch.float64),
        global_orient=poses[:, :3],
        body_pose=poses[:, 3:],
    )
    rot = axis_angle_to_matrix(torch.as_tensor(motion.Rh, dtype=torch.float64)).transpose(1, 2)
    th = torch.as_tensor(motion.Th, dtype=torch.float64)[:, None]
    assert torch.allclose(outputs["smpl"].vertices, ref.vertices @ rot + th, atol=1e-5)

    # Open body: the same world placement of its own joints; every frame stays a whole body.
    out = outputs["open"]
    assert out.vertices.shape == (24, open_body.num_vertices, 3)
    local = open_body(betas=torch.as_tensor(motion.betas, dtype=torch.float64), poses=poses)
    assert torch.allclose(out.joints, local.joints @ rot + th, atol=1e-9)
    # The motion's world is ZJU-MoCap's, z up: every frame is an upright whole body along z ...
    height = out.vertices[..., 2].amax(1) - out.vertices[..., 2].amin(1)
    assert torch.all(height > 1.3) and torch.all(height < 2.3)
    # ... whose pelvis follows Th over the ground plane (the walk moves it by more than that).
    pelvis_xy, th_xy = out.joints[:, 0, :2], th[:, 0, :2]
    assert float((pelvis_xy - th_xy).norm(dim=1).max()) < 0.1
    assert float((th_xy[-1] - th_xy[0]).norm()) > 0.2


def test_npz_sequences_and_amass_layout(tmp_path):
    motion = _walk(10, seed=2)
    save_smpl_params(tmp_path / "walk.npz", motion)
    loaded = load_smpl_params(tmp_path / "walk.npz")
    assert np.array_equal(loaded.poses, motion.poses) and loaded.fps == pytest.approx(30.0)
    hands = np.full((10, 90), 0.3, np.float32)  # SMPL-H hand joints, dropped on reading
    amass = {
        "poses": np.concatenate([motion.poses.reshape(10, 72)[:, :66], hands], 1),
        "trans": motion.Th,
        "betas": np.arange(16, dtype=np.float64),
        "mocap_framerate": np.float64(120),
    }
    np.savez(tmp_path / "amass.npz", **amass)
    loaded = load_smpl_params(tmp_path / "amass.npz")
    assert np.array_equal(loaded.poses[:, :22], motion.poses[:, :22]) and not loaded.poses[:, 22:].any()
    assert np.array_equal(loaded.Th, motion.Th) and not loaded.Rh.any() and loaded.fps == 120


class _Evil:
    def __reduce__(self):
        import os

        return (os.system, ("echo should-not-run",))


def test_bad_pose_files_are_named(tmp_path):
    evil = tmp_path / "0.npy"
    np.save(evil, np.array([_Evil()], dtype=object), allow_pickle=True)
    with pytest.raises(pickle.UnpicklingError, match="refusing"):
        load_smpl_params(evil)
    np.save(
        tmp_path / "1.npy",
        {
            "poses": np.zeros((1, 69)),
            "Rh": np.zeros((1, 3)),
            "Th": np.zeros((1, 3)),
            "shapes": np.zeros((1, 10)),
        },
    )
    with pytest.raises(ValueError, match="'poses' has shape"):
        load_smpl_params(tmp_path / "1.npy")
    np.save(
        tmp_path / "2.npy", {"poses": np.zeros((1, 72)), "Th": np.zeros((1, 3)), "shapes": np.zeros((1, 10))}
    )
    with pytest.raises(ValueError, match="missing 'Rh'"):
        load_smpl_params(tmp_path / "2.npy")
    with pytest.raises(FileNotFoundError):
        load_smpl_params(tmp_path / "nothing.npy")
