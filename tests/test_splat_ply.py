"""PLY export/import in the standard 3DGS layout: round trip, trimesh can read it, the byte
layout matches what the 3DGS reference writes, and broken files give clear errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from stg_node.splat import load_ply, rgb_to_sh, save_ply, sh_to_rgb
from stg_node.splat.ply import SH_C0
from stg_node.splat.scenes import person_sized_scene


def _scene(n=50, seed=0):
    scene = person_sized_scene(n, seed=seed)
    return scene.means, scene.quats, scene.scales, scene.opacities, scene.colors


def test_round_trip_keeps_every_parameter(tmp_path):
    means, quats, scales, opacities, colors = _scene()
    gen = torch.Generator().manual_seed(1)
    sh_rest = torch.randn(50, 15, 3, generator=gen) * 0.1
    path = save_ply(tmp_path / "avatar.ply", means, quats, scales, opacities, colors, sh_rest=sh_rest)
    back = load_ply(path)
    assert len(back) == 50
    np.testing.assert_allclose(back.means, means.numpy(), rtol=1e-7, atol=1e-7)
    np.testing.assert_allclose(back.quats, quats.numpy(), rtol=1e-7, atol=1e-7)
    np.testing.assert_allclose(back.scales, scales.numpy(), rtol=1e-5)
    np.testing.assert_allclose(back.opacities, opacities.numpy(), rtol=1e-5)
    np.testing.assert_allclose(back.colors, colors.numpy(), atol=1e-6)
    np.testing.assert_allclose(back.sh_rest, sh_rest.numpy(), atol=1e-7)


def test_layout_is_the_3dgs_one(tmp_path):
    """Property names and order, logit/log/wxyz encodings and channel-major f_rest, checked
    by reading the raw bytes with numpy (independent of load_ply)."""
    means = np.array([[1.0, 2.0, 3.0]])
    quats = np.array([[0.5, 0.5, -0.5, 0.5]])
    scales = np.array([[0.01, 0.02, 0.04]])
    opacities = np.array([0.25])
    sh_rest = np.arange(9, dtype=np.float64).reshape(1, 3, 3)  # K=3 bases x RGB
    path = save_ply(
        tmp_path / "one.ply", means, quats, scales, opacities, sh_dc=[[0.1, 0.2, 0.3]], sh_rest=sh_rest
    )
    raw = path.read_bytes()
    header, body = raw.split(b"end_header\n", 1)
    lines = header.decode().splitlines()
    assert lines[:2] == ["ply", "format binary_little_endian 1.0"]
    assert "element vertex 1" in lines
    names = [line.split()[2] for line in lines if line.startswith("property float")]
    expected = (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(9)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )
    assert names == expected
    values = dict(zip(names, np.frombuffer(body, dtype="<f4"), strict=True))
    assert values["opacity"] == pytest.approx(np.log(0.25 / 0.75), rel=1e-6)
    assert values["scale_2"] == pytest.approx(np.log(0.04), rel=1e-6)
    assert [values[f"rot_{i}"] for i in range(4)] == [0.5, 0.5, -0.5, 0.5]
    # channel-major: f_rest_0..2 are R of bases 0..2, then G, then B
    assert [values[f"f_rest_{i}"] for i in range(9)] == [0, 3, 6, 1, 4, 7, 2, 5, 8]
    assert values["nx"] == values["ny"] == values["nz"] == 0


def test_trimesh_reads_the_file(tmp_path):
    means, quats, scales, opacities, colors = _scene(200, seed=3)
    path = save_ply(tmp_path / "avatar.ply", means, quats, scales, opacities, colors)
    cloud = trimesh.load(path)
    assert isinstance(cloud, trimesh.PointCloud)
    np.testing.assert_allclose(np.asarray(cloud.vertices), means.numpy(), rtol=1e-6, atol=1e-6)
    raw = cloud.metadata["_ply_raw"]["vertex"]["data"]
    np.testing.assert_allclose(raw["f_dc_0"], rgb_to_sh(colors[:, 0].numpy()), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(raw["rot_3"], quats[:, 3].numpy())


def test_reads_ascii_and_big_endian_files_written_by_other_tools(tmp_path):
    means, quats, scales, opacities, colors = _scene(5)
    ref = load_ply(save_ply(tmp_path / "ref.ply", means, quats, scales, opacities, colors))
    props = [
        "x",
        "y",
        "z",
        "f_dc_0",
        "f_dc_1",
        "f_dc_2",
        "opacity",
        "scale_0",
        "scale_1",
        "scale_2",
        "rot_0",
        "rot_1",
        "rot_2",
        "rot_3",
    ]
    dc = rgb_to_sh(colors.double().numpy())
    logit = np.log(opacities.double().numpy() / (1 - opacities.double().numpy()))
    table = np.concatenate([means.numpy(), dc, logit[:, None], np.log(scales.numpy()), quats.numpy()], 1)
    header = "ply\nformat {}\nelement vertex 5\n" + "".join(f"property double {p}\n" for p in props)
    header += "end_header\n"
    (tmp_path / "a.ply").write_text(
        header.format("ascii 1.0") + "\n".join(" ".join(map(repr, r)) for r in table.tolist()) + "\n"
    )
    (tmp_path / "b.ply").write_bytes(
        header.format("binary_big_endian 1.0").encode() + table.astype(">f8").tobytes()
    )
    for name in ("a.ply", "b.ply"):
        got = load_ply(tmp_path / name)
        np.testing.assert_allclose(got.means, ref.means, rtol=1e-6)
        np.testing.assert_allclose(got.opacities, ref.opacities, rtol=1e-5)
        assert got.sh_rest.shape == (5, 0, 3)


def test_sh_colour_convention():
    rgb = np.array([0.0, 0.5, 1.0])
    assert np.allclose(rgb_to_sh(rgb), [-0.5 / SH_C0, 0.0, 0.5 / SH_C0])
    assert np.allclose(sh_to_rgb(rgb_to_sh(rgb)), rgb)


def test_extreme_values_are_clamped_not_written_as_inf(tmp_path):
    path = save_ply(
        tmp_path / "x.ply", [[0, 0, 0]], [[0, 0, 0, 0]], [[0, 1e-30, 2.0]], [1.0], [[0.5, 0.5, 0.5]]
    )
    raw = np.frombuffer(path.read_bytes().split(b"end_header\n", 1)[1], dtype="<f4")
    assert np.isfinite(raw).all()
    back = load_ply(path)
    assert back.opacities[0] == pytest.approx(1.0, abs=1e-6)
    assert back.scales[0, 2] == pytest.approx(2.0, rel=1e-6)


def test_bad_inputs_and_files_are_clear_errors(tmp_path):
    means, quats, scales, opacities, colors = _scene(4)
    with pytest.raises(ValueError, match=r"quats must be \[4, 4\]"):
        save_ply(tmp_path / "x.ply", means, quats[:, :3], scales, opacities, colors)
    with pytest.raises(ValueError, match="exactly one of colors"):
        save_ply(tmp_path / "x.ply", means, quats, scales, opacities)
    bad = means.clone()
    bad[0, 0] = float("nan")
    with pytest.raises(ValueError, match="means contains NaN"):
        save_ply(tmp_path / "x.ply", bad, quats, scales, opacities, colors)
    with pytest.raises(FileNotFoundError, match="no PLY file"):
        load_ply(tmp_path / "missing.ply")
    (tmp_path / "junk.ply").write_bytes(b"\x89PNG not a ply")
    with pytest.raises(ValueError, match="is not a PLY file"):
        load_ply(tmp_path / "junk.ply")
    good = save_ply(tmp_path / "good.ply", means, quats, scales, opacities, colors).read_bytes()
    (tmp_path / "cut.ply").write_bytes(good[:-10])
    with pytest.raises(ValueError, match="truncated"):
        load_ply(tmp_path / "cut.ply")
    (tmp_path / "noheader.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n")
    with pytest.raises(ValueError, match="no end_header"):
        load_ply(tmp_path / "noheader.ply")
    mesh_only = (
        "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
        "property float z\nend_header\n0 0 0\n"
    )
    (tmp_path / "mesh.ply").write_text(mesh_only)
    with pytest.raises(ValueError, match="missing properties f_dc_0"):
        load_ply(tmp_path / "mesh.ply")
