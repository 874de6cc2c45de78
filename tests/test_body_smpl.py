"""SMPL-format model files and forward pass, checked against the smplx package (independent oracle)."""

from __future__ import annotations

import logging
import pickle
import re

import numpy as np
import pytest
import torch
from smpl_fixtures import (
    ChumpyLeftover,
    random_smpl_arrays,
    real_world_extras,
    smpl_pkl_bytes,
    smplx_oracle,
    write_smpl_npz,
    write_smpl_pkl,
)

from stg_node.body import BodyModelError, axis_angle_to_matrix, load_body_model
from stg_node.body.smpl_io import accepted_file_names


@pytest.fixture(scope="module")
def smpl_arrays():
    return random_smpl_arrays(seed=3, num_verts=500)


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory, smpl_arrays):
    folder = tmp_path_factory.mktemp("smpl")
    write_smpl_pkl(folder / "basicmodel_neutral_lbs_10_207_0_v1.1.0.pkl", smpl_arrays)
    write_smpl_npz(folder / "model.npz", smpl_arrays)
    return folder


def _random_inputs(seed, batch, num_betas=10, dtype=torch.float64):
    rng = np.random.default_rng(seed)
    as_t = lambda a: torch.tensor(a, dtype=dtype)  # noqa: E731
    return (
        as_t(rng.normal(0, 1.0, (batch, num_betas))),
        as_t(rng.normal(0, 0.7, (batch, 72))),
        as_t(rng.normal(0, 1.0, (batch, 3))),
        as_t(rng.normal(0, 1.0, (batch, 3))),
    )


def _oracle_world(oracle, betas, poses, Rh, Th):
    out = oracle(betas=betas, global_orient=poses[:, :3], body_pose=poses[:, 3:])
    rot = axis_angle_to_matrix(Rh).transpose(1, 2)
    return out.vertices @ rot + Th[:, None], out.joints[:, :24] @ rot + Th[:, None]


@pytest.mark.parametrize("source", ["pkl", "npz"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_forward_matches_smplx(model_dir, smpl_arrays, source, dtype):
    path = model_dir if source == "pkl" else model_dir / "model.npz"
    model = load_body_model(path, dtype=dtype)
    oracle = smplx_oracle(smpl_arrays, dtype)
    betas, poses, Rh, Th = (t.to(dtype) for t in _random_inputs(7, batch=5))
    out = model(betas, poses, Rh, Th)
    ref_verts, ref_joints = _oracle_world(oracle, betas, poses, Rh, Th)
    assert out.vertices.shape == (5, 500, 3) and out.joints.shape == (5, 24, 3)
    assert torch.allclose(out.vertices, ref_verts, atol=1e-5, rtol=0)
    assert torch.allclose(out.joints, ref_joints, atol=1e-5, rtol=0)
    # Bone transforms are world transforms: they carry the rest joints onto the posed joints.
    rest = model.rest_joints(betas)
    moved = (out.bone_transforms[..., :3, :3] @ rest[..., None]).squeeze(-1) + out.bone_transforms[..., :3, 3]
    assert torch.allclose(moved, ref_joints, atol=1e-5, rtol=0)


def test_pose_blendshapes_off_matches_smplx_without_posedirs(model_dir, smpl_arrays):
    model = load_body_model(model_dir, dtype=torch.float64)
    arrays = dict(smpl_arrays, posedirs=np.zeros_like(smpl_arrays["posedirs"]))
    oracle = smplx_oracle(arrays, torch.float64)
    betas, poses, Rh, Th = _random_inputs(11, batch=3)
    ref_verts, _ = _oracle_world(oracle, betas, poses, Rh, Th)
    off = model(betas, poses, Rh, Th, pose_blendshapes=False).vertices
    on = model(betas, poses, Rh, Th, pose_blendshapes=True).vertices
    assert torch.allclose(off, ref_verts, atol=1e-6, rtol=0)
    assert (on - off).abs().max() > 1e-3  # the correctives really are applied when on


def test_pkl_and_npz_give_identical_buffers(model_dir):
    a = load_body_model(model_dir, dtype=torch.float64)
    b = load_body_model(model_dir / "model.npz", dtype=torch.float64)
    for name, buffer in a.named_buffers():
        assert torch.equal(buffer, dict(b.named_buffers())[name]), name


def test_old_protocol_pickle_with_copy_reg(tmp_path, smpl_arrays):
    path = tmp_path / "SMPL_FEMALE.pkl"
    write_smpl_pkl(path, smpl_arrays, protocol=1)  # objects go through copy_reg._reconstructor
    assert b"copy_reg" in path.read_bytes()
    model = load_body_model(tmp_path, gender="female", dtype=torch.float64)
    assert torch.allclose(model.shapedirs, torch.as_tensor(smpl_arrays["shapedirs"]))
    assert torch.allclose(model.J_regressor, torch.as_tensor(smpl_arrays["J_regressor"]))


def test_batch_broadcast_and_missing_inputs(model_dir):
    model = load_body_model(model_dir, dtype=torch.float64)
    betas, poses, Rh, Th = _random_inputs(5, batch=4)
    full = model(betas[:1].expand(4, -1), poses, Rh[:1].expand(4, -1), Th)
    broadcast = model(betas[0], poses.reshape(4, 24, 3), Rh[0], Th)
    assert torch.allclose(full.vertices, broadcast.vertices)
    rest = model()
    assert torch.allclose(rest.vertices[0], model.v_template)
    assert torch.allclose(rest.joints[0], model.J_regressor @ model.v_template)
    # Fewer betas than the model has are zero-padded.
    five = model(betas=betas[:, :5])
    padded = model(betas=torch.cat([betas[:, :5], torch.zeros(4, 5, dtype=betas.dtype)], 1))
    assert torch.allclose(five.vertices, padded.vertices)


def test_num_betas_truncates(model_dir):
    model = load_body_model(model_dir, num_betas=4)
    assert model.num_betas == 4 and model.shapedirs.shape[-1] == 4
    with pytest.raises(ValueError, match="4 shape directions"):
        model(betas=torch.ones(10))
    with pytest.raises(BodyModelError, match="has 10 shape directions"):
        load_body_model(model_dir, num_betas=11)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"poses": torch.zeros(2, 23, 3)}, "poses must be"),
        ({"Rh": torch.zeros(2, 4)}, "Rh must be"),
        ({"poses": torch.zeros(2, 72), "Th": torch.zeros(3, 3)}, "inconsistent batch"),
        ({"poses": torch.full((1, 72), float("nan"))}, "NaN"),
    ],
)
def test_bad_inputs_are_named(model_dir, kwargs, match):
    model = load_body_model(model_dir)
    with pytest.raises(ValueError, match=match):
        model(**kwargs)


def test_directory_name_resolution(tmp_path, smpl_arrays):
    for name in ("SMPL_MALE.pkl", "basicModel_f_lbs_10_207_0_v1.0.0.pkl", "smpl/SMPL_NEUTRAL.npz"):
        (tmp_path / name).parent.mkdir(exist_ok=True)
    write_smpl_pkl(tmp_path / "SMPL_MALE.pkl", smpl_arrays)
    write_smpl_pkl(tmp_path / "basicModel_f_lbs_10_207_0_v1.0.0.pkl", smpl_arrays)
    write_smpl_npz(tmp_path / "smpl" / "SMPL_NEUTRAL.npz", smpl_arrays)
    assert load_body_model(tmp_path, "male").name.endswith("SMPL_MALE.pkl")
    assert load_body_model(tmp_path, "female").name.endswith("basicModel_f_lbs_10_207_0_v1.0.0.pkl")
    assert load_body_model(tmp_path, "neutral").name.endswith("SMPL_NEUTRAL.npz")
    assert "SMPL_NEUTRAL.pkl" in accepted_file_names("neutral")
    assert "basicmodel_m_lbs_10_207_0_v1.1.0.pkl" in accepted_file_names("male")


def test_missing_file_says_what_to_do(tmp_path):
    with pytest.raises(BodyModelError) as err:
        load_body_model(tmp_path / "nowhere" / "SMPL_NEUTRAL.pkl")
    assert "smpl.is.tue.mpg.de" in str(err.value) and "SMPL_NEUTRAL.pkl" in str(err.value)
    with pytest.raises(BodyModelError) as err:
        load_body_model(tmp_path, gender="female")
    assert "basicModel_f_lbs_10_207_0_v1.0.0.pkl" in str(err.value) and "smpl.is.tue.mpg.de" in str(err.value)
    with pytest.raises(BodyModelError, match="gender"):
        load_body_model(tmp_path, gender="other")


def test_wrong_keys_and_shapes(tmp_path, smpl_arrays):
    broken = dict(smpl_arrays)
    del broken["weights"]
    write_smpl_npz(tmp_path / "a.npz", broken)
    with pytest.raises(BodyModelError, match="missing key.*weights"):
        load_body_model(tmp_path / "a.npz")
    bad_shape = dict(smpl_arrays, J_regressor=smpl_arrays["J_regressor"][:, :-1])
    write_smpl_npz(tmp_path / "b.npz", bad_shape)
    with pytest.raises(BodyModelError, match="J_regressor.*expected"):
        load_body_model(tmp_path / "b.npz")
    nan = dict(smpl_arrays, v_template=np.full_like(smpl_arrays["v_template"], np.nan))
    write_smpl_npz(tmp_path / "c.npz", nan)
    with pytest.raises(BodyModelError, match="NaN"):
        load_body_model(tmp_path / "c.npz")
    (tmp_path / "d.pkl").write_bytes(smpl_pkl_bytes(smpl_arrays)[:1000])
    with pytest.raises(BodyModelError, match="not a readable SMPL pickle"):
        load_body_model(tmp_path / "d.pkl")


@pytest.mark.parametrize(
    "joints, verts, pose_features, name",
    [(52, 6890, 459, "SMPL-H"), (55, 10475, 486, "SMPL-X"), (16, 778, 135, "MANO")],
)
def test_relatives_are_recognised(tmp_path, joints, verts, pose_features, name):
    rng = np.random.default_rng(0)
    weights = rng.uniform(size=(verts, joints))
    arrays = {
        "v_template": np.zeros((verts, 3)), "shapedirs": np.zeros((verts, 3, 10)),
        "posedirs": np.zeros((verts, 3, pose_features)), "J_regressor": np.zeros((joints, verts)),
        "weights": weights / weights.sum(1, keepdims=True), "kintree_table": np.zeros((2, joints), np.int64),
        "f": np.zeros((4, 3), np.int64),
    }  # fmt: skip
    write_smpl_npz(tmp_path / "x.npz", arrays)
    with pytest.raises(BodyModelError, match=f"unsupported body model variant.*{name}"):
        load_body_model(tmp_path / "x.npz")


class _Evil:
    def __reduce__(self):
        import os

        return (os.system, ("echo should-not-run",))


def test_pickle_with_foreign_globals_is_refused(tmp_path):
    path = tmp_path / "SMPL_NEUTRAL.pkl"
    path.write_bytes(pickle.dumps({"v_template": _Evil()}, protocol=2))
    with pytest.raises(
        BodyModelError, match="refusing to unpickle posix.system|refusing to unpickle os.system"
    ):
        load_body_model(path)


# --- users' files: extra arrays are ignored with one warning, required ones are checked ---------

WRITERS = {"pkl": write_smpl_pkl, "npz": write_smpl_npz}


def _warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]


def _ignored_names(message: str) -> set[str]:
    """The array names listed in the loader's 'ignoring N array(s) ...: name (why); ...' warning."""
    listed = message.split("does not use: ", 1)[1]
    return {match.group(1) for match in re.finditer(r"(?:^|; )(\w+) \(", listed)}


@pytest.mark.parametrize("source", ["pkl", "npz"])
def test_real_world_extras_are_ignored_with_one_warning(tmp_path, smpl_arrays, source, caplog):
    # An SMPL_NEUTRAL file as users have them: vt/ft, a per-corner uv (F, 3, 2), a chumpy
    # leftover, and the official extras J, bs_style, bs_type (random_smpl_arrays has those).
    path = tmp_path / f"SMPL_NEUTRAL.{source}"
    WRITERS[source](path, {**smpl_arrays, **real_world_extras(smpl_arrays, seed=5)})
    with caplog.at_level(logging.DEBUG, logger="stg_node.body.smpl_io"):
        model = load_body_model(tmp_path, dtype=torch.float64)
    warnings = _warnings(caplog)
    assert len(warnings) == 1, warnings
    assert _ignored_names(warnings[0]) == {"vt", "ft", "uv", "pose_leftover"}
    num_faces = len(smpl_arrays["f"])
    assert f"uv is ({num_faces}, 3, 2) float64, expected (Vt, 2)" in warnings[0]  # says why uv is unused
    assert str(path) in warnings[0]
    assert model.uv is None and model.uv_faces is None
    # The model is the one in the file: smplx (independent code) on the same arrays agrees.
    oracle = smplx_oracle(smpl_arrays, torch.float64)
    betas, poses, Rh, Th = _random_inputs(2, batch=2)
    ref_verts, _ = _oracle_world(oracle, betas, poses, Rh, Th)
    assert torch.allclose(model(betas, poses, Rh, Th).vertices, ref_verts, atol=1e-5, rtol=0)


def test_official_extras_and_the_open_body_load_without_a_warning(tmp_path, smpl_arrays, caplog):
    write_smpl_pkl(tmp_path / "SMPL_NEUTRAL.pkl", smpl_arrays)  # J, bs_style, bs_type, kintree_table
    with caplog.at_level(logging.DEBUG, logger="stg_node.body.smpl_io"):
        load_body_model(tmp_path)
        load_body_model(None)
    assert _warnings(caplog) == []
    assert any("bs_style" in r.getMessage() and r.levelno == logging.DEBUG for r in caplog.records)


@pytest.mark.parametrize("source", ["pkl", "npz"])
def test_a_missing_misshapen_or_valueless_required_array_is_named(tmp_path, smpl_arrays, source):
    extras = real_world_extras(smpl_arrays)
    write = WRITERS[source]
    broken = {**smpl_arrays, **extras}
    del broken["posedirs"]
    write(tmp_path / f"a.{source}", broken)
    with pytest.raises(BodyModelError, match=r"missing key\(s\) \['posedirs'\]"):
        load_body_model(tmp_path / f"a.{source}")
    misshapen = {**smpl_arrays, **extras, "weights": smpl_arrays["weights"][:-1]}
    write(tmp_path / f"b.{source}", misshapen)
    with pytest.raises(BodyModelError, match=r"'weights' has shape \(499, 24\), expected \(500, 24\)"):
        load_body_model(tmp_path / f"b.{source}")
    leftover = {**smpl_arrays, "v_template": ChumpyLeftover(smpl_arrays["v_template"])}
    write(tmp_path / f"c.{source}", leftover)
    with pytest.raises(BodyModelError, match="required 'v_template' is a chumpy expression without a stored"):
        load_body_model(tmp_path / f"c.{source}")


def test_our_own_texture_coordinates_are_still_checked_and_used(tmp_path, smpl_arrays, caplog):
    rng = np.random.default_rng(0)
    faces = smpl_arrays["f"]
    uv = {"uv": rng.uniform(0, 1, (50, 2)), "uv_faces": rng.integers(0, 50, faces.shape)}
    write_smpl_npz(tmp_path / "good.npz", {**smpl_arrays, **uv})
    model = load_body_model(tmp_path / "good.npz", dtype=torch.float64)
    assert torch.equal(model.uv, torch.as_tensor(uv["uv"])) and model.uv_faces.shape == faces.shape
    bad = {**smpl_arrays, **uv, "uv_faces": uv["uv_faces"] + 50}  # indexes past the end of uv
    write_smpl_npz(tmp_path / "bad.npz", bad)
    with caplog.at_level(logging.WARNING, logger="stg_node.body.smpl_io"):
        model = load_body_model(tmp_path / "bad.npz")
    assert model.uv is None and _ignored_names(_warnings(caplog)[0]) == {"uv", "uv_faces"}
