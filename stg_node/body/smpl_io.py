"""Reading SMPL-format model files: official ``.pkl`` pickles and ``.npz`` archives.

The official SMPL files are Python-2 pickles holding chumpy arrays and a scipy-sparse
``J_regressor``. We read them with neither chumpy nor scipy, through a restricted unpickler that
knows exactly the globals those files use (numpy array reconstruction, chumpy ``Ch`` objects,
scipy sparse matrices, ``copy_reg`` plumbing) and turns them into plain numpy arrays; any other
global in the stream is refused, so a model file cannot run code (the unpickler widens
:class:`stg_node.safe_load.SafeUnpickler`, the project's one safe loader). ``.npz`` files with the
same keys are read with ``allow_pickle=False``; a member holding pickled objects (chumpy leftovers
of a converted ``.pkl``) goes through the same restricted unpickler.

This module owns the file names we accept, the checks on keys and shapes, and the detection of
SMPL's relatives (SMPL-H, SMPL-X, MANO), which we name in the error instead of failing later.
Real files carry more than the model needs (texture coordinates ``vt``/``ft``, a per-corner
``uv`` (F, 3, 2), a precomputed ``J``, ``bs_style``/``bs_type``, SMPLify's priors): only a
missing or misshapen *required* array refuses a file; the rest is ignored, and whatever is not
a known SMPL-file extra is named in one warning.
"""

from __future__ import annotations

import logging
import pickle
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stg_node.safe_load import RefusedPickleError, SafeUnpickler, load_npz, safe_loads

log = logging.getLogger(__name__)

SMPL_NUM_JOINTS = 24
SMPL_PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21)
SMPL_JOINT_NAMES = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
    "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist", "left_hand", "right_hand",
)  # fmt: skip

GENDERS = ("neutral", "male", "female")
#: No value of a body model in metres (vertices, displacements per unit coefficient, regressor
#: weights) comes near this; a larger one is a damaged file, and would break the arithmetic.
MAX_MODEL_VALUE = 1e3
_GENDER_LETTER = {"neutral": "neutral", "male": "m", "female": "f"}
SMPL_DOWNLOAD_HINT = (
    "SMPL model files are licensed by their authors and are not shipped: register and download "
    "them from https://smpl.is.tue.mpg.de (SMPLify's SMPL_NEUTRAL.pkl comes from "
    "https://smplify.is.tue.mpg.de). Without them, use the open body: load_body_model(None)."
)

REQUIRED_KEYS = ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table", "f")
# Used when present and well-formed (the open body has them); ignored with the warning otherwise.
OPTIONAL_KEYS = ("uv", "uv_faces", "texture", "name")
# Found in official SMPL / SMPLify files and in the open body, and not needed: ignored without a
# warning (logged at debug level). ``J`` is recomputed from J_regressor so that it follows betas.
KNOWN_EXTRA_KEYS = (
    "J", "bs_style", "bs_type", "vert_sym_idxs", "J_regressor_prior", "weights_prior",
    "pose_training_info", "shape_labels", "source",
)  # fmt: skip

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


class SmplUnpickler(SafeUnpickler):
    """Unpickles SMPL model files; refuses every global they do not need."""

    allowed_description = (
        "an SMPL model file holds only numpy arrays, chumpy arrays and scipy sparse matrices"
    )

    def find_class(self, module: str, name: str):
        if module in ("copy_reg", "copyreg") and name == "_reconstructor":
            return _reconstructor
        if module.split(".")[0] == "chumpy":
            return _ChumpyStandIn
        if module.startswith("scipy.sparse") and name in _SPARSE_CLASSES:
            return _SPARSE_CLASSES[name]
        return super().find_class(module, name)


@dataclass(frozen=True)
class _Unreadable:
    """A value that could not become an array (a chumpy expression without a stored value)."""

    reason: str


def _to_numpy(key: str, value):
    """Chumpy and scipy stand-ins -> numpy; a value with no numbers in it -> :class:`_Unreadable`
    (an error later only if ``key`` is required)."""
    if isinstance(value, (_ChumpyStandIn, _SparseStandIn)):
        try:
            return value.to_numpy(key)
        except BodyModelError as exc:
            return _Unreadable(str(exc))
    return value


def read_pickle_model(path: Path) -> dict:
    """The arrays of an SMPL ``.pkl`` (Python 2 or 3 pickle) as a dict of numpy values."""
    raw = path.read_bytes()
    try:
        data = safe_loads(raw, SmplUnpickler)
    except RefusedPickleError as exc:
        raise BodyModelError(f"{path}: {exc}") from None
    except pickle.UnpicklingError as exc:
        raise BodyModelError(f"{path}: not a readable SMPL pickle ({exc})") from None
    except Exception as exc:  # truncated or corrupt stream
        raise BodyModelError(f"{path}: not a readable SMPL pickle ({type(exc).__name__}: {exc})") from None
    if not isinstance(data, dict):
        raise BodyModelError(f"{path}: expected a pickled dict of arrays, got {type(data).__name__}")
    return {str(k): _to_numpy(str(k), v) for k, v in data.items()}


def read_npz_model(path: Path) -> dict:
    """The arrays of an SMPL-format ``.npz``; object members (chumpy leftovers) go through
    :class:`SmplUnpickler`."""
    try:
        data = load_npz(path, unpickler=SmplUnpickler)
    except RefusedPickleError as exc:
        raise BodyModelError(str(exc)) from None  # names the file and the member
    except Exception as exc:
        raise BodyModelError(f"{path}: not a readable .npz archive ({type(exc).__name__}: {exc})") from None
    return {str(k): _to_numpy(str(k), v) for k, v in data.items()}


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
        value = data[key]
        if isinstance(value, _Unreadable):
            raise BodyModelError(f"{source}: required {value.reason}")
        try:
            return np.asarray(value, dtype=dtype)
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

    kintree = array("kintree_table", None)
    if kintree.ndim != 2 or kintree.shape != (2, SMPL_NUM_JOINTS):
        raise _shape_error(source, "kintree_table", kintree, "(2, 24)")
    parents = kintree[0].astype(np.int64)
    parents[0] = -1  # stored as 2**32 - 1 in the official files
    if np.any(parents[1:] < 0) or np.any(parents[1:] >= np.arange(1, SMPL_NUM_JOINTS)):
        raise BodyModelError(
            f"{source}: kintree_table parents {parents.tolist()} are not a tree in SMPL order"
        )

    faces = array("f", None)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise _shape_error(source, "f", faces, "(F, 3)")
    faces = faces.astype(np.int64)
    if not faces.size:
        raise BodyModelError(f"{source}: 'f' holds no faces (expected (F, 3) with F >= 1: a surface)")
    if faces.min() < 0 or faces.max() >= num_verts:
        raise BodyModelError(f"{source}: faces index vertices outside [0, {num_verts})")

    for key, value in (("v_template", v_template), ("shapedirs", shapedirs), ("posedirs", posedirs),
                       ("J_regressor", j_regressor), ("weights", weights)):  # fmt: skip
        if not np.all(np.isfinite(value)):
            raise BodyModelError(f"{source}: {key!r} contains NaN or infinite values")
        peak = float(np.abs(value).max()) if value.size else 0.0
        if peak > MAX_MODEL_VALUE:  # metres of a body, or displacements per unit coefficient
            raise BodyModelError(
                f"{source}: {key!r} has values up to {peak:.3g}, beyond the plausible +-{MAX_MODEL_VALUE:g} "
                "(a body in metres)"
            )
    sums = weights.sum(axis=1)
    if np.abs(sums - 1).max() > 1e-3:
        raise BodyModelError(
            f"{source}: skinning weights must sum to 1 per vertex "
            f"(found sums in [{sums.min():.4f}, {sums.max():.4f}])"
        )

    optional = _optional_arrays(data, faces.shape)
    _report_ignored(data, optional.ignored, source)
    return ModelArrays(
        v_template=v_template, shapedirs=shapedirs, posedirs=posedirs, J_regressor=j_regressor,
        weights=weights, parents=parents, faces=faces, uv=optional.uv, uv_faces=optional.uv_faces,
        texture=optional.texture, name=optional.name,
    )  # fmt: skip


@dataclass
class _OptionalArrays:
    uv: np.ndarray | None = None
    uv_faces: np.ndarray | None = None
    texture: np.ndarray | None = None
    name: str = "smpl"
    ignored: dict[str, str] = field(default_factory=dict)  # optional key -> why it was not used


def _uv_problem(uv, uv_faces, faces_shape: tuple[int, ...]) -> str | None:
    """Why ``uv``/``uv_faces`` cannot be our texture coordinates, or None if they can."""
    if np.ndim(uv) != 2 or np.shape(uv)[1] != 2:
        return f"uv is {_describe(uv)}, expected (Vt, 2) indexed by uv_faces"
    if np.shape(uv_faces) != tuple(faces_shape):
        return (
            f"uv_faces is {_describe(uv_faces)}, expected {tuple(faces_shape)} (one uv index per face corner)"
        )
    uv_faces = np.asarray(uv_faces)
    if uv_faces.size and (uv_faces.min() < 0 or uv_faces.max() >= len(uv)):
        return f"uv_faces index outside uv's {len(uv)} rows"
    return None


def _optional_arrays(data: dict, faces_shape: tuple[int, ...]) -> _OptionalArrays:
    """uv + uv_faces, texture and name where present and well-formed; the reason for each one that is not."""
    out = _OptionalArrays()
    if "uv" in data or "uv_faces" in data:
        problem = _uv_problem(data.get("uv"), data.get("uv_faces"), faces_shape)
        if problem is None:
            out.uv = np.asarray(data["uv"], dtype=np.float64)
            out.uv_faces = np.asarray(data["uv_faces"], dtype=np.int64)
        else:
            out.ignored.update({key: problem for key in ("uv", "uv_faces") if key in data})
    if "texture" in data:
        texture = data["texture"]
        if (
            isinstance(texture, np.ndarray)
            and texture.dtype == np.uint8
            and texture.ndim == 3
            and (texture.shape[2] == 3)
        ):
            out.texture = texture
        else:
            out.ignored["texture"] = f"texture is {_describe(texture)}, expected (H, W, 3) uint8"
    if "name" in data:
        out.name = str(np.asarray(data["name"]))
    return out


def _report_ignored(data: dict, optional_ignored: dict[str, str], source: str) -> None:
    """One warning naming every array of ``data`` the model does not use (known SMPL extras: debug only)."""
    used = set(REQUIRED_KEYS) | set(OPTIONAL_KEYS)
    known = sorted(k for k in data if k in KNOWN_EXTRA_KEYS)
    unknown = {
        k: (v.reason if isinstance(v, _Unreadable) else _describe(v))
        for k, v in data.items()
        if k not in used and k not in KNOWN_EXTRA_KEYS
    }
    unknown.update(optional_ignored)
    if known:
        log.debug("%s: not used (known SMPL-file extras): %s", source, ", ".join(known))
    if unknown:
        listed = "; ".join(f"{key} ({why})" for key, why in sorted(unknown.items()))
        log.warning("%s: ignoring %d array(s) the body model does not use: %s", source, len(unknown), listed)


def _describe(value) -> str:
    if value is None:
        return "missing"
    if isinstance(value, np.ndarray):
        return f"{value.shape} {value.dtype}"
    return type(value).__name__


def read_model_file(path: Path) -> ModelArrays:
    """Read and validate one ``.pkl`` or ``.npz`` SMPL-format model file."""
    if path.suffix.lower() == ".pkl":
        data = read_pickle_model(path)
    elif path.suffix.lower() == ".npz":
        data = read_npz_model(path)
    else:
        raise BodyModelError(f"{path}: an SMPL model file must be .pkl or .npz")
    return validate_model_arrays(data, str(path))
