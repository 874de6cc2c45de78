"""Random SMPL-format model files for tests, in the real formats (no licensed data involved).

``write_smpl_pkl`` imitates the official files: a Python-2-style protocol-2 pickle (strings as
latin-1 byte strings), ``shapedirs`` as a chumpy ``Ch`` object (a stand-in class registered as
``chumpy.ch.Ch`` only while pickling) and ``J_regressor`` as a scipy ``csc_matrix``.
"""

from __future__ import annotations

import collections
import contextlib
import io
import pickle
import struct
import sys
import types

import numpy as np

from stg_node.body.smpl_io import SMPL_PARENTS


def random_smpl_arrays(seed: int = 0, num_verts: int = 400, num_betas: int = 10) -> dict:
    """A random but well-formed SMPL-format model: a rough humanoid joint layout, sparse weights."""
    rng = np.random.default_rng(seed)
    joints = np.zeros((24, 3))
    offsets = {1: (0.07, -0.09, 0), 2: (-0.07, -0.09, 0), 3: (0, 0.11, 0), 4: (0.03, -0.38, 0),
               5: (-0.03, -0.38, 0), 6: (0, 0.13, 0), 7: (0, -0.40, -0.03), 8: (0, -0.40, -0.03),
               9: (0, 0.06, 0), 10: (0, -0.06, 0.12), 11: (0, -0.06, 0.12), 12: (0, 0.21, 0),
               13: (0.08, 0.11, 0), 14: (-0.08, 0.11, 0), 15: (0, 0.06, 0.05), 16: (0.1, 0.0, 0),
               17: (-0.1, 0.0, 0), 18: (0.26, 0, 0), 19: (-0.26, 0, 0), 20: (0.25, 0, 0),
               21: (-0.25, 0, 0), 22: (0.08, 0, 0), 23: (-0.08, 0, 0)}  # fmt: skip
    for j in range(1, 24):
        joints[j] = joints[SMPL_PARENTS[j]] + np.asarray(offsets[j])
    joints += (0.0, -0.24, 0.03)
    owner = rng.integers(0, 24, num_verts)
    v_template = joints[owner] + rng.normal(0, 0.05, (num_verts, 3))
    weights = np.zeros((num_verts, 24))
    for k in range(3):  # up to 3 influences: own joint, parent, one random
        cols = (
            owner
            if k == 0
            else (np.asarray(SMPL_PARENTS)[owner].clip(0) if k == 1 else rng.integers(0, 24, num_verts))
        )
        weights[np.arange(num_verts), cols] += rng.uniform(0.2, 1.0, num_verts)
    weights /= weights.sum(1, keepdims=True)
    regressor = np.zeros((24, num_verts))
    for j in range(24):
        idx = rng.choice(num_verts, 8, replace=False)
        regressor[j, idx] = rng.uniform(0.1, 1, 8)
    regressor /= regressor.sum(1, keepdims=True)
    kintree = np.zeros((2, 24), dtype=np.uint32)
    kintree[0] = np.asarray(SMPL_PARENTS, dtype=np.int64) % (2**32)
    kintree[1] = np.arange(24)
    return {
        "v_template": v_template,
        "shapedirs": rng.normal(0, 0.01, (num_verts, 3, num_betas)),
        "posedirs": rng.normal(0, 0.005, (num_verts, 3, 207)),
        "J_regressor": regressor,
        "weights": weights,
        "kintree_table": kintree,
        "f": rng.integers(0, num_verts, (2 * num_verts, 3)).astype(np.uint32),
        "J": regressor @ v_template,
        "bs_style": "lbs",
        "bs_type": "lrotmin",
    }


class _Py2Pickler(pickle._Pickler):
    """Writes str and bytes as Python 2 byte strings (BINSTRING), as the official files have them."""

    dispatch = dict(pickle._Pickler.dispatch)

    def _save_py2_string(self, obj):
        data = obj.encode("latin1") if isinstance(obj, str) else bytes(obj)
        if len(data) < 256:
            self.write(pickle.SHORT_BINSTRING + struct.pack("<B", len(data)) + data)
        else:
            self.write(pickle.BINSTRING + struct.pack("<i", len(data)) + data)
        self.memoize(obj)

    dispatch[str] = _save_py2_string
    dispatch[bytes] = _save_py2_string

    # Module paths as a Python 2 / old numpy and scipy wrote them.
    _PY2_MODULES = {
        "numpy._core.multiarray": "numpy.core.multiarray",
        "scipy.sparse._csc": "scipy.sparse.csc",
        "builtins": "__builtin__",
        "copyreg": "copy_reg",
    }

    def save_global(self, obj, name=None):
        module = pickle.whichmodule(obj, obj.__qualname__)
        module = self._PY2_MODULES.get(module, module)
        name = name or obj.__qualname__
        self.write(pickle.GLOBAL + f"{module}\n{name}\n".encode("ascii"))
        self.memoize(obj)

    dispatch[type] = save_global


class ChumpyLeftover:
    """Marks a value to be written as a chumpy expression holding no value of its own (e.g. a
    transpose of a Ch), what an official file keeps where chumpy computed something lazily."""

    def __init__(self, value):
        self.value = np.asarray(value)


def _stand_in_chumpy():
    chumpy = types.ModuleType("chumpy")
    chumpy_ch = types.ModuleType("chumpy.ch")
    chumpy_reordering = types.ModuleType("chumpy.reordering")

    class Ch:
        def __init__(self, x):
            self.x = x
            self._dirty_vars = set()
            self._itr = None

        def __getstate__(self):
            return {"x": self.x, "_dirty_vars": self._dirty_vars, "_itr": self._itr}

    class transpose:  # noqa: N801 (chumpy's own name)
        def __init__(self, a):
            self.a = Ch(a)
            self.axes = None

        def __getstate__(self):
            return {"a": self.a, "axes": self.axes, "_dirty_vars": set()}

    Ch.__module__ = "chumpy.ch"
    Ch.__qualname__ = "Ch"
    transpose.__module__ = "chumpy.reordering"
    transpose.__qualname__ = "transpose"
    chumpy_ch.Ch = Ch
    chumpy_reordering.transpose = transpose
    chumpy.ch = chumpy_ch
    chumpy.reordering = chumpy_reordering
    return {"chumpy": chumpy, "chumpy.ch": chumpy_ch, "chumpy.reordering": chumpy_reordering}


@contextlib.contextmanager
def _chumpy_importable():
    """Our stand-in chumpy module while pickling, so objects pickle under chumpy's class paths."""
    modules = _stand_in_chumpy()
    saved = {name: sys.modules.get(name) for name in modules}
    sys.modules.update(modules)
    try:
        yield modules
    finally:
        for name, module in saved.items():
            if module is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = module


def _leftovers_to_chumpy(arrays: dict, modules: dict) -> dict:
    transpose = modules["chumpy.reordering"].transpose
    return {k: transpose(v.value) if isinstance(v, ChumpyLeftover) else v for k, v in arrays.items()}


def smpl_pkl_bytes(arrays: dict, protocol: int = 2) -> bytes:
    import scipy.sparse

    with _chumpy_importable() as modules:
        data = _leftovers_to_chumpy(arrays, modules)
        data["shapedirs"] = modules["chumpy.ch"].Ch(np.asarray(arrays["shapedirs"]))
        data["J_regressor"] = scipy.sparse.csc_matrix(arrays["J_regressor"])
        buffer = io.BytesIO()
        _Py2Pickler(buffer, protocol=protocol).dump(data)
        return buffer.getvalue()


def write_smpl_pkl(path, arrays: dict, protocol: int = 2) -> None:
    path.write_bytes(smpl_pkl_bytes(arrays, protocol))


def write_smpl_npz(path, arrays: dict) -> None:
    """Plain arrays; a :class:`ChumpyLeftover` becomes a pickled chumpy object in an object member
    (what ``np.savez(**smpl_dict)`` writes when the dict still holds chumpy objects)."""
    with _chumpy_importable() as modules:
        data = _leftovers_to_chumpy(arrays, modules)
        np.savez(path, **{k: np.asarray(v) if isinstance(v, np.ndarray | list | str) else _object_array(v)
                          for k, v in data.items()})  # fmt: skip


def _object_array(value) -> np.ndarray:
    holder = np.empty((), dtype=object)
    holder[()] = value
    return holder


def real_world_extras(arrays: dict, seed: int = 0) -> dict:
    """What users' SMPL files carry beside the model: texture coordinates as ``vt``/``ft`` (OBJ
    naming) and as a per-corner ``uv`` (F, 3, 2), and a chumpy leftover with no stored value.
    (``random_smpl_arrays`` already has ``J``, ``bs_style``, ``bs_type`` and ``kintree_table``.)"""
    rng = np.random.default_rng(seed)
    num_faces = len(arrays["f"])
    return {
        "vt": rng.uniform(0, 1, (num_faces // 2, 2)),
        "ft": rng.integers(0, num_faces // 2, (num_faces, 3)).astype(np.uint32),
        "uv": rng.uniform(0, 1, (num_faces, 3, 2)),
        "pose_leftover": ChumpyLeftover(rng.normal(size=(4, 3))),
    }


def smplx_oracle(arrays: dict, dtype):
    """The smplx package's SMPL built from the same arrays (an independent implementation)."""
    import smplx

    struct_ = types.SimpleNamespace(**{k: np.asarray(v) for k, v in arrays.items()})
    return smplx.SMPL(
        model_path=None, data_struct=struct_, num_betas=arrays["shapedirs"].shape[-1], dtype=dtype,
        vertex_ids=collections.defaultdict(int), create_transl=False,
    )  # fmt: skip
