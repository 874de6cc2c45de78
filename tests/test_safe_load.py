"""Every file a user brings loads through stg_node.safe_load: a crafted file runs nothing.

Each test writes a real file format (ZJU-MoCap annots.npy and new_params, SMPL .pkl/.npz,
THuman4.0 and folder-format .npz, LPIPS weights, a torch checkpoint, a launch YAML, a bus
header) carrying a payload that creates a marker file when deserialised naively, reads it the
way stg_node does, and checks for a clear error and no marker. ``test_payloads_are_live`` shows
the payloads do run under plain pickle, so the other tests can fail.
"""

from __future__ import annotations

import os
import pickle
import shlex
from pathlib import Path

import msgpack
import numpy as np
import pytest
import torch
import yaml
from smpl_fixtures import random_smpl_arrays, write_smpl_npz, write_smpl_pkl

from stg_node.body import BodyModelError, load_body_model, load_smpl_params
from stg_node.bus import MessageError
from stg_node.bus.codec import decode, encode
from stg_node.data import DatasetError, open_dataset
from stg_node.data.flow import FlowCache
from stg_node.data.metrics import lpips_weights
from stg_node.safe_load import (
    RefusedPickleError,
    load_npy,
    load_npz,
    load_torch,
    load_yaml,
    safe_loads,
    unpack_msgpack,
)
from tests.bus.bushelpers import sample_messages
from tests.fixtures.datasets import write_folder, write_thuman4, write_zju_original


class RunsCommand:
    """Pickles as ``os.system("touch MARKER")``."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {shlex.quote(str(self.marker))}",))


class OpensFile:
    """Pickles as ``open(MARKER, "w")``: creates the file without a shell."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (open, (str(self.marker), "w"))


PAYLOADS = {"os.system": RunsCommand, "open": OpensFile}


@pytest.fixture(params=list(PAYLOADS))
def evil(request, tmp_path):
    """(payload object, marker path); the test asserts the marker never appears."""
    marker = tmp_path / "pwned"
    yield PAYLOADS[request.param](marker), marker
    assert not marker.exists(), "the crafted file ran code"


def test_payloads_are_live(tmp_path):
    for make in PAYLOADS.values():
        marker = tmp_path / f"live-{make.__name__}"
        result = pickle.loads(pickle.dumps(make(marker)))
        if hasattr(result, "close"):
            result.close()
        assert marker.exists(), make.__name__
        marker.unlink()


# --- the loaders themselves ----------------------------------------------------------------------


def test_npy_object_array_and_bare_pickle_are_refused(tmp_path, evil):
    payload, _ = evil
    path = tmp_path / "dict.npy"
    np.save(path, {"poses": np.zeros(3), "x": payload}, allow_pickle=True)
    with pytest.raises(RefusedPickleError, match=rf"{path}.*refusing to unpickle"):
        load_npy(path)
    bare = tmp_path / "bare.npy"
    bare.write_bytes(pickle.dumps({"x": payload}))
    with pytest.raises(RefusedPickleError, match="refusing"):
        load_npy(bare)


def test_npy_plain_arrays_and_dicts_still_load(tmp_path):
    from collections import OrderedDict

    plain = np.arange(12, dtype=np.float32).reshape(3, 4)
    np.save(tmp_path / "plain.npy", plain)
    assert np.array_equal(load_npy(tmp_path / "plain.npy"), plain)
    data = {"a": plain, "nested": [{"b": np.int64(3)}, (1.5, "s")], "o": OrderedDict(k=np.ones(2))}
    np.save(tmp_path / "dict.npy", data, allow_pickle=True)
    loaded = load_npy(tmp_path / "dict.npy")
    assert np.array_equal(loaded["a"], plain) and loaded["nested"][0]["b"] == 3
    assert loaded["nested"][1] == (1.5, "s") and np.array_equal(loaded["o"]["k"], np.ones(2))
    (tmp_path / "bare.npy").write_bytes(pickle.dumps({"a": plain}, protocol=2))
    assert np.array_equal(load_npy(tmp_path / "bare.npy")["a"], plain)


def test_npz_pickled_member_is_refused_with_or_without_an_unpickler(tmp_path, evil):
    payload, _ = evil
    path = tmp_path / "params.npz"
    np.savez(path, poses=np.zeros((2, 72)), extra=np.array([payload], dtype=object))
    with pytest.raises(RefusedPickleError, match="'extra'.*pickled Python objects"):
        load_npz(path)
    from stg_node.safe_load import SafeUnpickler

    with pytest.raises(RefusedPickleError, match="'extra'.*refusing to unpickle"):
        load_npz(path, unpickler=SafeUnpickler)
    np.savez(tmp_path / "ok.npz", a=np.ones(3), b=np.array({"k": 1}, dtype=object))
    assert load_npz(tmp_path / "ok.npz", unpickler=SafeUnpickler)["b"] == {"k": 1}


# --- datasets ------------------------------------------------------------------------------------


def test_zju_annots_npy_is_refused(tmp_path, evil):
    payload, _ = evil
    root = tmp_path / "CoreView_377"
    root.mkdir()
    write_zju_original(root, num_frames=2, num_cams=2)
    annots = load_npy(root / "annots.npy")
    annots["cams"]["K"][0] = payload
    np.save(root / "annots.npy", annots, allow_pickle=True)
    with pytest.raises(DatasetError, match="annots.npy: refused: refusing to unpickle") as err:
        open_dataset(root, "zju", size=None)
    assert err.value.path == root / "annots.npy"


def test_zju_new_params_npy_is_refused(tmp_path, evil):
    payload, _ = evil
    root = tmp_path / "CoreView_377"
    root.mkdir()
    write_zju_original(root, num_frames=2, num_cams=2)
    params = load_npy(root / "new_params" / "1.npy")
    params["Th"] = payload
    np.save(root / "new_params" / "1.npy", params, allow_pickle=True)
    with pytest.raises(DatasetError, match=r"1\.npy: refused: refusing to unpickle"):
        open_dataset(root, "zju", size=None, check=True)
    with pytest.raises(RefusedPickleError, match=r"1\.npy: refusing to unpickle"):
        load_smpl_params(root / "new_params")


def test_thuman4_smpl_params_npz_is_refused(tmp_path, evil):
    payload, _ = evil
    root = tmp_path / "subject00"
    write_thuman4(root, num_frames=2, num_cams=2)
    arrays = load_npz(root / "smpl_params.npz")
    np.savez(root / "smpl_params.npz", **{**arrays, "expression": np.array([payload], dtype=object)})
    with pytest.raises(DatasetError, match="smpl_params.npz: refused: .*'expression'"):
        open_dataset(root, "thuman4", size=None)


def test_folder_poses_npz_is_refused(tmp_path, evil):
    payload, _ = evil
    root = tmp_path / "capture"
    write_folder(root, num_frames=2)
    arrays = load_npz(root / "poses.npz")
    np.savez(root / "poses.npz", **{**arrays, "betas": np.array(payload, dtype=object)})
    with pytest.raises(DatasetError, match="poses.npz: refused: .*'betas'"):
        open_dataset(root, "folder", size=None)


def test_flow_cache_file_is_recomputed_not_run(tmp_path, evil):
    payload, _ = evil
    cache = FlowCache(tmp_path / "flow")
    cache.directory.mkdir()
    rng = np.random.default_rng(0)
    a, b = (rng.integers(0, 255, (24, 32, 3), dtype=np.uint8) for _ in range(2))
    np.savez(cache.path(cache.key(a, b, None, None)), forward=np.array([payload], dtype=object))
    pair = cache.get(a, b)
    assert cache.dropped == 1 and pair.forward.shape == (24, 32, 2)


# --- body models and pose files ------------------------------------------------------------------


def test_smpl_pkl_and_npz_are_refused(tmp_path, evil):
    payload, _ = evil
    arrays = random_smpl_arrays(seed=1, num_verts=60)
    write_smpl_pkl(tmp_path / "SMPL_NEUTRAL.pkl", {**arrays, "J": payload})
    with pytest.raises(BodyModelError, match=r"SMPL_NEUTRAL\.pkl: refusing to unpickle"):
        load_body_model(tmp_path / "SMPL_NEUTRAL.pkl")
    write_smpl_npz(tmp_path / "SMPL_NEUTRAL.npz", {**arrays, "J": np.array([payload], dtype=object)})
    with pytest.raises(BodyModelError, match=r"SMPL_NEUTRAL\.npz member 'J': refusing to unpickle"):
        load_body_model(tmp_path / "SMPL_NEUTRAL.npz")


# --- LPIPS weights, torch files, YAML, msgpack --------------------------------------------------


def test_lpips_weights_are_refused(tmp_path, evil):
    payload, _ = evil
    weights = {"lin.0.weight": np.array([payload], dtype=object)}
    np.savez(lpips_weights.weights_path("alex", tmp_path), **weights)
    with pytest.raises(lpips_weights.LpipsWeightsError, match="unreadable.*refusing"):
        lpips_weights.load_state("alex", tmp_path)
    # The installer's flax pickles go through the same unpickler.
    with pytest.raises(RefusedPickleError, match="refusing to unpickle"):
        lpips_weights.convert_flax_checkpoint("alex", safe_loads(pickle.dumps({"AlexNet_0": payload})))


def test_torch_files_load_weights_only(tmp_path, evil):
    payload, _ = evil
    torch.save({"w": torch.ones(2)}, tmp_path / "ok.pt")
    assert torch.equal(load_torch(tmp_path / "ok.pt")["w"], torch.ones(2))
    torch.save({"w": torch.ones(2), "x": payload}, tmp_path / "evil.pt")
    with pytest.raises(pickle.UnpicklingError, match="Weights only load failed"):
        load_torch(tmp_path / "evil.pt")


def test_yaml_python_tags_are_refused(tmp_path):
    marker = tmp_path / "pwned"
    path = tmp_path / "launch.yaml"
    path.write_text(f"nodes:\n  - !!python/object/apply:os.system ['touch {marker}']\n")
    with pytest.raises(yaml.YAMLError, match="python/object/apply"):
        load_yaml(path)
    assert not marker.exists()
    (tmp_path / "ok.yaml").write_text("nodes:\n  - name: tracker\n    rate: 30\n")
    assert load_yaml(tmp_path / "ok.yaml") == {"nodes": [{"name": "tracker", "rate": 30}]}


def test_msgpack_extension_types_are_refused():
    packed = msgpack.packb({"a": msgpack.ExtType(42, b"\x00")})
    with pytest.raises(ValueError, match="extension type 42 refused"):
        unpack_msgpack(packed)
    assert unpack_msgpack(msgpack.packb({"a": [1, "b"]})) == {"a": [1, "b"]}
    # The bus decodes every header with it: a header with an extension value is a counted drop.
    frames = encode(sample_messages()["BodyPose"], topic="body/pose", seq=0, src="t", stamp_ns=1)
    header = msgpack.unpackb(frames[1])
    header["src"] = msgpack.ExtType(1, b"x")
    with pytest.raises(MessageError) as err:
        decode([frames[0], msgpack.packb(header), *frames[2:]])
    assert err.value.reason == "malformed"
