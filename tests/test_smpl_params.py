"""One SMPL-parameter type: checked on construction, torch-free, and the same numbers everywhere.

The synthetic benchmark writes its poses, the ZJU-MoCap loader reads them back as
:class:`SmplParams`, the bus carries them as BodyPose, and the body poses a mesh from them:
the same parameters must give the same vertices on every route, in the frames docs/BODY.md
states (the body's canonical space is SMPL's, y up; the benchmark's world is ZJU-MoCap's, z up).
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from stg_node.body import drive_body, load_body_model
from stg_node.body.params import SmplParams, SmplSequence
from stg_node.bus import BodyPose
from stg_node.bus.codec import decode, encode
from stg_node.data import open_dataset
from stg_node.data.synth import writer
from stg_node.data.synth.generate import SynthConfig, generate
from stg_node.data.types import SmplParams as DataSmplParams

ROOT = Path(__file__).resolve().parents[1]


def _params(seed: int = 0, num_betas: int = 10, model: str = "smpl") -> SmplParams:
    rng = np.random.default_rng(seed)
    return SmplParams(
        poses=rng.normal(0, 0.4, (24, 3)),
        Rh=rng.normal(0, 1, 3),
        Th=rng.normal(0, 1, 3),
        betas=rng.normal(0, 1, num_betas),
        model=model,
    )


# --- the type --------------------------------------------------------------------------------------


def test_data_and_body_share_one_class():
    assert DataSmplParams is SmplParams


def test_fields_become_float32_of_the_documented_shapes():
    flat = np.arange(72, dtype=np.float64) / 100
    params = SmplParams(poses=flat, Rh=[0, 0, 1], Th=(1, 2, 3), betas=np.zeros(16))
    assert params.poses.shape == (24, 3) and np.array_equal(params.poses.reshape(-1), flat.astype(np.float32))
    for name in ("poses", "Rh", "Th", "betas"):
        assert getattr(params, name).dtype == np.float32, name
    assert params.model == "smpl" and params.betas.shape == (16,)


@pytest.mark.parametrize(
    "fields, message",
    [
        ({"poses": np.zeros((23, 3))}, r"SmplParams.poses has shape \(23, 3\), expected \(24, 3\)"),
        ({"Rh": np.zeros(4)}, r"SmplParams.Rh has shape \(4,\), expected \(3,\)"),
        ({"Th": np.array([0, np.nan, 0])}, "SmplParams.Th contains NaN"),
        ({"betas": np.zeros(0)}, "betas is empty"),
        ({"betas": np.zeros((1, 10))}, r"SmplParams.betas has shape \(1, 10\), expected \(N,\)"),
        ({"poses": "pose"}, "SmplParams.poses is not numeric"),
        ({"model": "mano"}, "model must be one of"),
    ],
)
def test_bad_fields_are_named(fields, message):
    good = {"poses": np.zeros((24, 3)), "Rh": np.zeros(3), "Th": np.zeros(3), "betas": np.zeros(10)}
    with pytest.raises(ValueError, match=message):
        SmplParams(**{**good, **fields})


def test_a_sequence_is_its_frames_stacked():
    frames = [_params(seed) for seed in range(5)]
    seq = SmplSequence.from_frames(frames, fps=25.0, source="test")
    assert len(seq) == 5 and seq.poses.shape == (5, 24, 3) and seq.betas.shape == (5, 10)
    for i, frame in enumerate(seq):
        for name in ("poses", "Rh", "Th", "betas"):
            assert np.array_equal(getattr(frame, name), getattr(frames[i], name)), (i, name)
    assert np.array_equal(seq[-1].Th, frames[4].Th)
    part = seq[1:4]
    assert isinstance(part, SmplSequence) and len(part) == 3 and part.fps == 25.0
    assert np.array_equal(part.poses[0], frames[1].poses)
    zeros = np.zeros((3, 3))
    shared = SmplSequence(poses=np.zeros((3, 72)), Rh=zeros, Th=zeros, betas=np.ones(10))
    assert shared.poses.shape == (3, 24, 3) and shared.betas_per_frame.shape == (3, 10)
    assert np.array_equal(shared[2].betas, np.ones(10, np.float32))
    with pytest.raises(ValueError, match=r"SmplSequence.Th has shape \(2, 3\), expected \(3, 3\)"):
        dataclasses.replace(shared, Th=np.zeros((2, 3)))
    with pytest.raises(IndexError, match="frame 3 out of range"):
        shared.frame(3)
    with pytest.raises(ValueError, match="mix body models"):
        SmplSequence.from_frames([_params(0), _params(1, model="smplx")])


def test_importing_the_type_imports_no_torch():
    check = textwrap.dedent(
        """
        import sys
        import stg_node.body.params, stg_node.data.types
        from stg_node.body import SmplParams, SmplSequence
        import stg_node.bus
        pose = stg_node.bus.BodyPose.from_smpl(SmplParams([0.0] * 72, [0, 0, 0], [0, 0, 1], [0.0] * 10))
        assert pose.to_smpl().Th[2] == 1
        print("torch" in sys.modules)
        """
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    result = subprocess.run([sys.executable, "-c", check], cwd=ROOT, env=env, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "False"


# --- the bus -----------------------------------------------------------------------------------------


def _over_the_wire(pose: BodyPose) -> BodyPose:
    return decode(encode(pose, topic="body/pose", seq=3, src="test", stamp_ns=1))


@pytest.mark.parametrize("num_betas", [1, 10, 300])
def test_body_pose_round_trip_is_exact(num_betas):
    params = _params(seed=num_betas, num_betas=num_betas)
    pose = BodyPose.from_smpl(params, frame_seq=7, frame_index=2, time=0.5, confidence=0.9)
    received = _over_the_wire(pose)
    assert (received.frame_seq, received.frame_index, received.time, received.confidence) == (7, 2, 0.5, 0.9)
    back = received.to_smpl()
    for name in ("poses", "Rh", "Th", "betas"):
        assert getattr(back, name).dtype == np.float32
        assert np.array_equal(getattr(back, name), getattr(params, name)), name
    assert back.model == "smpl"


def test_body_pose_refuses_what_it_cannot_carry():
    with pytest.raises(ValueError, match="'smplx' parameters"):
        BodyPose.from_smpl(_params(model="smplx"))
    with pytest.raises(TypeError, match="takes SmplParams"):
        BodyPose.from_smpl({"poses": np.zeros((24, 3))})


def test_smplx_fits_become_the_nearest_smpl_parameters_the_bus_carries():
    """The shared joints and the placement carry over, the hands rest, the shape is SMPL's mean."""
    from stg_node.body import smplx_as_smpl

    fit = _params(model="smplx")
    converted = smplx_as_smpl(fit)
    assert converted.model == "smpl" and fit.model == "smplx"  # the input is left alone
    assert np.array_equal(converted.poses[:22], fit.poses[:22]) and not converted.poses[22:].any()
    assert np.array_equal(converted.Rh, fit.Rh) and np.array_equal(converted.Th, fit.Th)
    assert np.array_equal(converted.betas, np.zeros(10, np.float32))
    assert BodyPose.from_smpl(converted).to_smpl().model == "smpl"
    assert smplx_as_smpl(converted) is converted  # SMPL stays as it is
    assert smplx_as_smpl(fit, num_betas=16).betas.shape == (16,)
    with pytest.raises(ValueError, match="num_betas"):
        smplx_as_smpl(fit, num_betas=0)


# --- the synthetic benchmark, the dataset loader, the body and the bus agree --------------------


@pytest.fixture(scope="module")
def body():
    return load_body_model()


@pytest.fixture(scope="module")
def benchmark(tmp_path_factory, body):
    out = tmp_path_factory.mktemp("synth") / "walk"
    config = SynthConfig(out=out, seed=3, num_frames=4, size=32, motion="walk", num_novel_views=0)
    generate(dataclasses.replace(config, supersample=1), body=body, progress=False)
    return out


def test_benchmark_poses_give_the_same_vertices_on_every_route(benchmark, body):
    dataset = open_dataset(benchmark, "zju", "all", size=None)
    meta = writer.read_metadata(benchmark)
    assert meta["world"]["up"] == [0.0, 0.0, 1.0]
    for frame in dataset.frames:
        loaded = dataset.smpl(frame)  # what the trainer gets
        wired = _over_the_wire(BodyPose.from_smpl(loaded)).to_smpl()  # what a tracker would send
        with torch.no_grad():
            via_loader = drive_body(body, loaded).vertices[0]
            via_bus = drive_body(body, wired).vertices[0]
        assert torch.equal(via_loader, via_bus)
        # The generator's own ground truth (skinning + garment): equal away from the garment.
        truth = torch.from_numpy(np.load(benchmark / "new_vertices" / f"{frame}.npy"))
        distance = (truth - via_loader).norm(dim=1)
        assert float(distance.quantile(0.5)) < 1e-5
        # Frames: the dataset's world is z up (feet on z = 0, the body standing along +z) ...
        extent = via_loader.amax(0) - via_loader.amin(0)
        assert 1.3 < float(extent[2]) < 2.3 and float(via_loader[:, 2].amin()) == pytest.approx(0, abs=1e-4)
        # ... the body's canonical space is SMPL's, y up: the same pose without Rh/Th stands along y.
        canonical = dataclasses.replace(loaded, Rh=np.zeros(3), Th=np.zeros(3))
        with torch.no_grad():
            local = drive_body(body, canonical).vertices[0]
        local_extent = local.amax(0) - local.amin(0)
        assert float(local_extent[1]) > 1.3 and float(local_extent[1]) > 2 * float(local_extent[2])
