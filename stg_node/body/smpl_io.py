"""Reading SMPL-format model files: official ``.pkl`` pickles and ``.npz`` archives.

The official SMPL files are Python-2 pickles holding chumpy arrays and a scipy-sparse
``J_regressor``. We read them with neither chumpy nor scipy, through a restricted unpickler that
knows exactly the globals those files use (numpy array reconstruction, chumpy ``Ch`` objects,
scipy sparse matrices, ``copy_reg`` plumbing) and turns them into plain numpy arrays; any other
global in the stream is refused, so a model file cannot run code. ``.npz`` files with the same
keys are read with ``allow_pickle=False``.

This module owns the file names we accept, the checks on keys and shapes, and the detection of
SMPL's relatives (SMPL-H, SMPL-X, MANO), which we name in the error instead of failing later.
"""

from __future__ import annotations

import io
import pickle
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stg_node.body.safe_pickle import NumpyUnpickler

SMPL_NUM_JOINTS = 24
SMPL_PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21)
SMPL_JOINT_NAMES = (
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_hand",
    "right_hand",
)

GENDERS = ("neutral", "male", "female")
_GENDER_LETTER = {"neutral": "neutral", "male": "m", "female": "f"}
SMPL_DOWNLOAD_HINT = (
    "SMPL model files are licensed by their authors and are not shipped: register and download "
    "them from https://smpl.is.tue.mpg.de (SMPLify's SMPL_NEUTRAL.pkl comes from "
    "https://smplify.is.tue.mpg.de). Without them, use the open body: load_body_model(None)."
)

REQUIRED_KEYS = ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table", "f")

# Known relatives, recognised by joint count (weights' columns) and vertex count.
_VARIANTS = {
    52: "SMPL-H (SMPL+H, 52 joints with hands)",
    55: "SMPL-X (55 joints with hands and face)",
    16: "MANO (a hand model, 16 joints)",
    5: "FLAME (a head model, 5 joints)",
}


class BodyModelError(ValueError):
    """A body model file is missing, unreadable, or not an SMPL-format model."""


def accepted_file_names(gender: str) -> list[str]:
    """The file names looked for in a directory, in order of preference, for one gender."""
    if gender not in GENDERS:
        raise BodyModelError(f"gender must be one of {GENDERS}, got {gender!r}")
    letter = _GENDER_LETTER[gender]
    names = []
    for ext in ("pkl", "npz"):
        names += [
            f"SMPL_{gender.upper()}.{ext}",
            f"basicmodel_{letter}_lbs_10_207_0_v1.1.0.{ext}",
            f"basicModel_{letter}_lbs_10_207_0_v1.0.0.{ext}",
        ]
    return names


def _name_pattern(gender: str) -> re.Pattern:
    letter = _GENDER_LETTER[gender]
    return re.compile(
        rf"^(smpl_{gender}|basicmodel_{letter}_lbs_10_207_0_v1\.[0-9]\.[0-9])\.(pkl|npz)$", re.IGNORECASE
    )


def resolve_model_file(path: str | Path, gender: str = "neutral") -> Path:
    """A model file from a file path, or from a directory holding the usual SMPL names.

    A directory is searched directly and in ``smpl/`` below it (the smplx package's layout),
    case-insensitively, for the names of :func:`accepted_file_names`.
    """
    path = Path(path).expanduser()
    accepted = accepted_file_names(gender)
    if path.is_file():
        if path.suffix.lower() not in (".pkl", ".npz"):
            raise BodyModelError(f"{path}: an SMPL model file must be .pkl or .npz")
        return path
    if path.is_dir():
        pattern = _name_pattern(gender)
        for folder in (path, path / "smpl", path / "SMPL"):
            if not folder.is_dir():
                continue
            found = sorted(p for p in folder.iterdir() if p.is_file() and pattern.match(p.name))
            if found:
                # Prefer .pkl (the official form) and the names in accepted order.
                order = {name.lower(): i for i, name in enumerate(accepted)}
                found.sort(key=lambda p: order.get(p.name.lower(), len(order)))
                return found[0]
        raise BodyModelError(
            f"no {gender} SMPL model in directory {path} (nor in {path / 'smpl'}); accepted names: "
            f"{', '.join(accepted)}. {SMPL_DOWNLOAD_HINT}"
        )
    raise BodyModelError(
        f"SMPL model not found: {path} does not exist. Pass a .pkl/.npz file or a directory holding one "
        f"of: {', '.join(accepted)}. {SMPL_DOWNLOAD_HINT}"
    )


# --------------------------------------------------------------------------------------------
# Restricted unpickling of the official files
# --------------------------------------------------------------------------------------------


class _ChumpyStandIn:
    """Receives the state of a pickled chumpy object; only its value (``x``) is kept."""

    _state = None

    def __init__(self, *args, **kwargs):
        pass

    def __setstate__(self, state):
        self._state = state

    def to_numpy(self, key: str) -> np.ndarray:
        state = self._state
        if isinstance(state, tuple) and len(state) == 2 and isinstance(state[1], dict):
            state = {**(state[0] or {}), **state[1]}
        if isinstance(state, dict):
            for name in ("x", "_x", "r"):
                value = state.get(name)
                if isinstance(value, np.ndarray):
                    return value
        raise BodyModelError(
            f"{key!r} is a chumpy expression without a stored value (keys: "
            f"{sorted(state) if isinstance(state, dict) else type(state).__name__}); convert the file with "
            "chumpy installed (x.r for every chumpy array) and save it as .npz"
        )


class _SparseStandIn:
    """Receives the state of a pickled scipy.sparse matrix and densifies it with numpy alone."""

    _format = None  # set per subclass: csc, csr or coo
    _state = None

    def __init__(self, *args, **kwargs):
        pass

    def __setstate__(self, state):
        self._state = state

    def to_numpy(self, key: str) -> np.ndarray:
        state = self._state if isinstance(self._state, dict) else {}
        shape = state.get("_shape", state.get("shape"))
        fmt = self._format
        data = state.get("data")
        if shape is None or data is None:
            raise BodyModelError(f"{key!r}: unreadable scipy.sparse matrix state (keys {sorted(state)})")
        rows, cols = int(shape[0]), int(shape[1])
        dense = np.zeros((rows, cols), dtype=np.asarray(data).dtype)
        data = np.asarray(data)
        if fmt in ("csc", "csr"):
            indptr, indices = np.asarray(state["indptr"]), np.asarray(state["indices"])
            major = np.repeat(np.arange(len(indptr) - 1), np.diff(indptr))
            if fmt == "csc":
                np.add.at(dense, (indices, major), data)
            else:
                np.add.at(dense, (major, indices), data)
        elif fmt == "coo":
            row = np.asarray(state.get("row", state.get("coords", (None, None))[0]))
            col = np.asarray(state.get("col", state.get("coords", (None, None))[1]))
            np.add.at(dense, (row, col), data)
        else:
            raise BodyModelError(f"{key!r}: unsupported scipy.sparse format {fmt!r}")
        return dense


_SPARSE_CLASSES = {
    f"{fmt}_{kind}": type(f"_Sparse_{fmt}", (_SparseStandIn,), {"_format": fmt})
    for fmt in ("csc", "csr", "coo")
    for kind in ("matrix", "array")
}


def _reconstructor(cls, base, state):
    """copy_reg._reconstructor for the classes we allow (our stand-ins and numpy types only)."""
    if base is not object or not issubclass(cls, (_ChumpyStandIn, _SparseStandIn)):
        raise pickle.UnpicklingError(f"refusing to reconstruct {cls!r} from {base!r}")
    return object.__new__(cls)


class _RestrictedUnpickler(NumpyUnpickler):
    """Unpickles SMPL model files; refuses every global they do not need."""

    def find_class(self, module: str, name: str):
        if module in ("copy_reg", "copyreg") and name == "_reconstructor":
            return _reconstructor
        if module.split(".")[0] == "chumpy":
            return _ChumpyStandIn
        if module.startswith("scipy.sparse") and name in _SPARSE_CLASSES:
            return _SPARSE_CLASSES[name]
        try:
            return super().find_class(module, name)
        except pickle.UnpicklingError:
            raise pickle.UnpicklingError(
                f"refusing to unpickle {module}.{name}: an SMPL model file holds only numpy arrays, chumpy "
                "arrays and scipy sparse matrices"
            ) from None


def _to_numpy(key: str, value):
    if isinstance(value, (_ChumpyStandIn, _SparseStandIn)):
        return value.to_numpy(key)
    return value


def read_pickle_model(path: Path) -> dict:
    """The arrays of an SMPL ``.pkl`` (Python 2 or 3 pickle) as a dict of numpy values."""
    raw = path.read_bytes()
    try:
        data = _RestrictedUnpickler(io.BytesIO(raw), encoding="latin1").load()
    except pickle.UnpicklingError as exc:
        if str(exc).startswith("refusing"):
            raise BodyModelError(f"{path}: {exc}") from None
        raise BodyModelError(f"{path}: not a readable SMPL pickle ({exc})") from None
    except Exception as exc:  # truncated or corrupt stream
        raise BodyModelError(f"{path}: not a readable SMPL pickle ({type(exc).__name__}: {exc})") from None
    if not isinstance(data, dict):
        raise BodyModelError(f"{path}: expected a pickled dict of arrays, got {type(data).__name__}")
    return {str(k): _to_numpy(str(k), v) for k, v in data.items()}


def read_npz_model(path: Path) -> dict:
    """The arrays of an SMPL-format ``.npz`` (no pickled objects allowed)."""
    try:
        with np.load(path, allow_pickle=False) as archive:
            return {k: archive[k] for k in archive.files}
    except ValueError as exc:
        raise BodyModelError(
            f"{path}: holds pickled objects, which we do not load from .npz ({exc}); "
            "re-save it with plain arrays"
        ) from None
    except Exception as exc:
        raise BodyModelError(f"{path}: not a readable .npz archive ({type(exc).__name__}: {exc})") from None


# --------------------------------------------------------------------------------------------
# Validation into a typed set of arrays
# --------------------------------------------------------------------------------------------


@dataclass
class ModelArrays:
    """The arrays of an SMPL-format model, checked and in the layouts BodyModel uses."""

    v_template: np.ndarray  # (V, 3) float64
    shapedirs: np.ndarray  # (V, 3, S)
    posedirs: np.ndarray  # (V, 3, 207) as in the files
    J_regressor: np.ndarray  # (24, V) dense
    weights: np.ndarray  # (V, 24)
    parents: np.ndarray  # (24,) int64, parents[0] = -1
    faces: np.ndarray  # (F, 3) int64
    uv: np.ndarray | None = None  # (Vt, 2) in [0, 1]
    uv_faces: np.ndarray | None = None  # (F, 3)
    texture: np.ndarray | None = None  # (H, W, 3) uint8
    name: str = "smpl"


def _shape_error(source: str, key: str, value, expected: str) -> BodyModelError:
    return BodyModelError(f"{source}: {key!r} has shape {tuple(np.shape(value))}, expected {expected}")


def validate_model_arrays(data: dict, source: str) -> ModelArrays:
    """Check keys, shapes and values of a loaded model; name SMPL-H/SMPL-X/MANO if that is what it is."""
    missing = [k for k in REQUIRED_KEYS if k not in data]
    if missing:
        extra = ""
        if "hands_components" in data or "hands_componentsl" in data:
            extra = " (it looks like an SMPL-H/MANO file)"
        raise BodyModelError(
            f"{source}: not an SMPL-format model{extra}: missing key(s) {missing}; an SMPL file holds "
            f"{list(REQUIRED_KEYS)}"
        )

    def array(key, dtype=np.float64):
        try:
            return np.asarray(data[key], dtype=dtype)
        except (TypeError, ValueError) as exc:
            raise BodyModelError(f"{source}: {key!r} is not numeric ({exc})") from None

    weights = array("weights")
    v_template = array("v_template")
    if weights.ndim != 2:
        raise _shape_error(source, "weights", weights, "(V, 24)")
    num_joints = weights.shape[1]
    if num_joints != SMPL_NUM_JOINTS:
        variant = _VARIANTS.get(num_joints)
        if variant is None and v_template.shape[0] == 10475:
            variant = _VARIANTS[55]
        what = f"this is {variant}" if variant else f"it has {num_joints} joints"
        raise BodyModelError(
            f"{source}: unsupported body model variant: {what}; stg_node needs SMPL (24 joints, "
            f"6890 vertices in the official model). {SMPL_DOWNLOAD_HINT.split(':')[0]}."
        )
    if v_template.ndim != 2 or v_template.shape[1] != 3:
        raise _shape_error(source, "v_template", v_template, "(V, 3)")
    num_verts = v_template.shape[0]
    if weights.shape[0] != num_verts:
        raise _shape_error(source, "weights", weights, f"({num_verts}, 24)")

    shapedirs = array("shapedirs")
    if shapedirs.ndim == 2 and shapedirs.shape[0] == num_verts * 3:
        shapedirs = shapedirs.reshape(num_verts, 3, -1)
    if shapedirs.ndim != 3 or shapedirs.shape[:2] != (num_verts, 3):
        raise _shape_error(source, "shapedirs", shapedirs, f"({num_verts}, 3, S)")

    posedirs = array("posedirs")
    num_pose = (SMPL_NUM_JOINTS - 1) * 9
    if posedirs.ndim == 2 and posedirs.shape == (num_pose, num_verts * 3):  # smplx's in-memory layout
        posedirs = posedirs.T.reshape(num_verts, 3, num_pose)
    if posedirs.ndim != 3 or posedirs.shape != (num_verts, 3, num_pose):
        if (
            posedirs.ndim == 3
            and posedirs.shape[:2] == (num_verts, 3)
            and posedirs.shape[2] in (459, 486, 135)
        ):
            raise BodyModelError(
                f"{source}: posedirs have {posedirs.shape[2]} pose features: not an SMPL model"
            )
        raise _shape_error(source, "posedirs", posedirs, f"({num_verts}, 3, {num_pose})")

    j_regressor = array("J_regressor")
    if j_regressor.shape != (SMPL_NUM_JOINTS, num_verts):
        raise _shape_error(source, "J_regressor", j_regressor, f"(24, {num_verts})")

    kintree = np.asarray(data["kintree_table"])
    if kintree.ndim != 2 or kintree.shape != (2, SMPL_NUM_JOINTS):
        raise _shape_error(source, "kintree_table", kintree, "(2, 24)")
    parents = kintree[0].astype(np.int64)
    parents[0] = -1  # stored as 2**32 - 1 in the official files
    if np.any(parents[1:] < 0) or np.any(parents[1:] >= np.arange(1, SMPL_NUM_JOINTS)):
        raise BodyModelError(
            f"{source}: kintree_table parents {parents.tolist()} are not a tree in SMPL order"
        )

    faces = np.asarray(data["f"])
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise _shape_error(source, "f", faces, "(F, 3)")
    faces = faces.astype(np.int64)
    if faces.size and (faces.min() < 0 or faces.max() >= num_verts):
        raise BodyModelError(f"{source}: faces index vertices outside [0, {num_verts})")

    for key, value in (
        ("v_template", v_template),
        ("shapedirs", shapedirs),
        ("posedirs", posedirs),
        ("J_regressor", j_regressor),
        ("weights", weights),
    ):
        if not np.all(np.isfinite(value)):
            raise BodyModelError(f"{source}: {key!r} contains NaN or infinite values")
    sums = weights.sum(axis=1)
    if np.abs(sums - 1).max() > 1e-3:
        raise BodyModelError(
            f"{source}: skinning weights must sum to 1 per vertex "
            f"(found sums in [{sums.min():.4f}, {sums.max():.4f}])"
        )

    uv = uv_faces = texture = None
    if "uv" in data:
        uv = np.asarray(data["uv"], dtype=np.float64)
        uv_faces = np.asarray(data["uv_faces"], dtype=np.int64) if "uv_faces" in data else None
        if uv.ndim != 2 or uv.shape[1] != 2:
            raise _shape_error(source, "uv", uv, "(Vt, 2)")
        if uv_faces is None or uv_faces.shape != faces.shape:
            raise _shape_error(source, "uv_faces", uv_faces, f"{faces.shape} (one UV index per face corner)")
    if "texture" in data:
        texture = np.asarray(data["texture"])
        if texture.ndim != 3 or texture.shape[2] != 3 or texture.dtype != np.uint8:
            raise BodyModelError(
                f"{source}: 'texture' must be (H, W, 3) uint8, got {texture.shape} {texture.dtype}"
            )
    name = str(np.asarray(data["name"])) if "name" in data else "smpl"
    return ModelArrays(
        v_template=v_template,
        shapedirs=shapedirs,
        posedirs=posedirs,
        J_regressor=j_regressor,
        weights=weights,
        parents=parents,
        faces=faces,
        uv=uv,
        uv_faces=uv_faces,
        texture=texture,
        name=name,
    )


def read_model_file(path: Path) -> ModelArrays:
    """Read and validate one ``.pkl`` or ``.npz`` SMPL-format model file."""
    if path.suffix.lower() == ".pkl":
        data = read_pickle_model(path)
    elif path.suffix.lower() == ".npz":
        data = read_npz_model(path)
    else:
        raise BodyModelError(f"{path}: an SMPL model file must be .pkl or .npz")
    return validate_model_arrays(data, str(path))
