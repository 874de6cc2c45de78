"""Damaged files users hand us: what tools/fuzz_inputs.py found crashing, kept as tests, and a reduced
fuzz run of every format (each damaged file a one-line error naming it, exit 1 or 2; never a
traceback, a hang or a crash)."""

from __future__ import annotations

import io
import json
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from smpl_fixtures import random_smpl_arrays, write_smpl_npz

from stg_node.body import BodyModelError, load_body_model
from stg_node.body.params import SmplParams
from stg_node.data import DatasetError, open_dataset
from stg_node.launch import LaunchFileError, read_launch
from stg_node.safe_load import UnreadableFileError, load_npy, load_npz
from tests.fixtures.datasets import write_folder, write_thuman4

ROOT = Path(__file__).resolve().parents[1]


def _huge_header() -> bytes:
    """An .npy that promises a 1M x 1M float32 array (4 TB) and holds 16 bytes."""
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buf, {"descr": "<f4", "fortran_order": False, "shape": (1 << 20, 1 << 20)}
    )
    return buf.getvalue() + b"\0" * 16


def test_an_array_header_promising_terabytes_is_refused_before_anything_is_allocated(tmp_path):
    npy = tmp_path / "a.npy"
    npy.write_bytes(_huge_header())
    with pytest.raises(UnreadableFileError, match=r"a\.npy: its header promises a 1048576x1048576 float32"):
        load_npy(npy)
    npz = tmp_path / "b.npz"
    with zipfile.ZipFile(npz, "w") as z:
        z.writestr("poses.npy", _huge_header())
    with pytest.raises(UnreadableFileError, match=r"b\.npz member 'poses'.*16 bytes follow"):
        load_npz(npz)


@pytest.mark.parametrize("content", [b"", b"PK", b"\x93NUMPY", b"not a zip at all, nor an array"])
def test_empty_cut_or_foreign_npy_and_npz_files_are_named(tmp_path, content):
    for name, reader in (("x.npz", load_npz), ("x.npy", load_npy)):
        path = tmp_path / name
        path.write_bytes(content)
        with pytest.raises(ValueError, match=name.replace(".", r"\.")):
            reader(path)


def test_a_launch_file_alias_bomb_deep_nesting_and_no_nodes_are_refused(tmp_path):
    bomb = ['a0: &a0 ["x", "x", "x", "x", "x", "x", "x", "x", "x"]']
    for i in range(1, 12):
        bomb.append(f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 7) + "]")  # 9 * 7**11 values
    path = tmp_path / "bomb.yaml"
    path.write_text("nodes: [{name: a, cmd: [true]}]\nbomb:\n" + "\n".join("  " + b for b in bomb) + "\n")
    with pytest.raises(LaunchFileError, match=r"bomb\.yaml:\d+: expands to more than 100000 values"):
        read_launch(path)
    deep = tmp_path / "deep.yaml"
    deep.write_text("nodes: [{name: a, cmd: [true]}]\ndeep: " + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(LaunchFileError, match=r"deep\.yaml.*nested"):
        read_launch(deep)
    for text in ("", "# only a comment\n", "description: nothing\n"):
        empty = tmp_path / "empty.yaml"
        empty.write_text(text)
        with pytest.raises(LaunchFileError, match=r"empty\.yaml.*nothing to launch"):
            read_launch(empty)


def test_implausible_smpl_magnitudes_are_refused_by_the_type_and_the_datasets(tmp_path):
    z = np.zeros(3, np.float32)
    with pytest.raises(ValueError, match="Th has values up to 1e\\+30 m, beyond the plausible"):
        SmplParams(poses=np.zeros((24, 3)), Rh=z, Th=z + 1e30, betas=np.zeros(10))
    SmplParams(poses=np.full((24, 3), 7.0), Rh=z + 40.0, Th=z + 900.0, betas=np.zeros(10))  # unusual, fine
    root = tmp_path / "capture"
    write_folder(root, num_frames=2)
    with np.load(root / "poses.npz") as data:
        arrays = dict(data)
    arrays["Th"] = arrays["Th"] * 1e30
    np.savez(root / "poses.npz", **arrays)
    with pytest.raises(DatasetError, match=r"poses\.npz .*Th has values up to"):
        open_dataset(root, "folder")[0]


def test_a_body_model_without_faces_or_with_absurd_values_is_named(tmp_path):
    arrays = random_smpl_arrays(num_verts=200)
    write_smpl_npz(tmp_path / "nofaces.npz", {**arrays, "f": np.zeros((0, 3), np.int64)})
    with pytest.raises(BodyModelError, match=r"nofaces\.npz: 'f' holds no faces"):
        load_body_model(tmp_path / "nofaces.npz")
    write_smpl_npz(tmp_path / "huge.npz", {**arrays, "v_template": arrays["v_template"] * 1e30})
    with pytest.raises(BodyModelError, match=r"huge\.npz: 'v_template' has values up to"):
        load_body_model(tmp_path / "huge.npz")


def test_dataset_json_of_the_wrong_types_is_a_named_error(tmp_path):
    folder = tmp_path / "folder"
    write_folder(folder, num_frames=2)
    doc = json.loads((folder / "cameras.json").read_text())
    doc["cameras"]["front"]["width"] = "wide"
    (folder / "cameras.json").write_text(json.dumps(doc))
    with pytest.raises(DatasetError, match=r"cameras\.json: front\.width is 'wide'"):
        open_dataset(folder, "folder")[0]
    doc["cameras"]["front"] = None
    (folder / "cameras.json").write_text(json.dumps(doc))
    with pytest.raises(DatasetError, match=r"cameras\.json: camera 'front' is NoneType"):
        open_dataset(folder, "folder")
    thuman = tmp_path / "thuman"
    write_thuman4(thuman, num_frames=2, num_cams=1)
    calib = json.loads((thuman / "calibration.json").read_text())
    calib["cam00"]["imgSize"] = 7
    (thuman / "calibration.json").write_text(json.dumps(calib))
    with pytest.raises(DatasetError, match=r"calibration\.json: camera cam00 imgSize is 7"):
        open_dataset(thuman, "thuman4")[0]


def test_bytes_after_a_recordings_footer_do_not_stop_it_being_read(tmp_path):
    from stg_node.bus.codec import encode
    from stg_node.bus.recording import BagReader, BagWriter
    from tests.bus.bushelpers import sample_messages

    path = tmp_path / "s.mcap"
    with BagWriter(path) as bag:
        for k in range(3):
            msg = sample_messages(k)["RenderedImage"]
            bag.write_frames(
                encode(msg, topic="avatar/image", seq=k, src="t", stamp_ns=10**18 + k), 10**18 + k
            )
    path.write_bytes(path.read_bytes() + b"\x4c" + b"\xfe" * 96)  # a record length of ~2**63
    assert [m.topic for m in BagReader(path).messages()] == ["avatar/image"] * 3


def test_a_calibration_that_is_not_a_camera_is_refused_by_the_ingest(tmp_path):
    from stg_node.nodes.sources import Calibration, SourceError

    for name, doc, words in (
        ("nan.json", {"K": [[float("nan"), 0, 1], [0, 1, 1], [0, 0, 1]]}, "finite"),
        (
            "mirror.json",
            {"K": [[60, 0, 32], [0, 60, 32], [0, 0, 1]], "R": [[-1, 0, 0], [0, 1, 0], [0, 0, 1]]},
            "rotation",
        ),
        ("flat.json", {"K": [[0, 0, 0], [0, 0, 0], [0, 0, 1]]}, "fx, fy > 0"),
    ):
        (tmp_path / name).write_text(json.dumps(doc))
        with pytest.raises(SourceError, match=f"{name}: .*{words}"):
            Calibration.from_file(tmp_path / name)
    (tmp_path / "binary.json").write_bytes(b"\xff\xfe\x00{")
    from stg_node.tracking.camera import IntrinsicsError, load_intrinsics

    with pytest.raises(IntrinsicsError, match=r"binary\.json: cannot be read as JSON"):
        load_intrinsics(tmp_path / "binary.json", 64, 64)


def test_a_reduced_fuzz_run_over_every_format_finds_nothing(tmp_path):
    """tools/fuzz_inputs.py, a few random cases per format (the full run is in docs/SECURITY.md)."""
    result = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "fuzz_inputs.py"), "--no-fixed", "--cases", "3", "--seed", "5",
         "--work", str(tmp_path / "work"), "--json", str(tmp_path / "fuzz.json")],
        cwd=ROOT, capture_output=True, text=True, timeout=900,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
    cases = json.loads((tmp_path / "fuzz.json").read_text())
    formats = {c["format"] for c in cases}
    assert formats >= {"launch", "poses", "zju", "thuman4", "folder", "smpl", "mcap", "intrinsics"}
    assert all(not c["verdict"].startswith("FAILED") for c in cases)
