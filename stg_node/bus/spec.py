"""Building blocks of message schemas: wire dtypes, envelope limits, scalar and array field specs.

proto/envelope.yaml is the language-neutral statement of everything here; the message
classes in :mod:`stg_node.bus.messages` are assembled from these specs, and
tests/test_bus_proto.py checks the two against each other. Validation lives on the specs
themselves so that encoding (a node's bug raises at publish) and decoding (a peer's bad
message is a counted drop) apply exactly the same rules.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np

# --- envelope -----------------------------------------------------------------------------

#: Version of the envelope itself (frame layout + header keys); proto/envelope.yaml.
ENVELOPE_VERSION = 1
#: Keys every header carries; a message's own scalar fields may not use these names.
ENVELOPE_KEYS = ("type", "v", "seq", "stamp_ns", "src", "arrays")

MAX_TOPIC_BYTES = 255
MAX_HEADER_BYTES = 64 * 1024
MAX_SRC_CHARS = 128
MAX_ARRAYS = 128
MAX_NDIM = 8
#: The largest single buffer any message type may carry; also the transport cap
#: (ZMQ_MAXMSGSIZE) on every receiving socket, so a peer cannot make us allocate more.
MAX_FRAME_BYTES = 1 << 30
#: Bounds on scalar header values, so a 64 KiB header cannot hide a huge structure.
MAX_STR_CHARS = 4096
MAX_MAP_ENTRIES = 256
MAX_INT = (1 << 63) - 1
MIN_INT = -(1 << 63)

#: Wire dtype names (always little-endian) -> numpy dtypes.
WIRE_DTYPES: dict[str, np.dtype] = {
    "uint8": np.dtype("u1"),
    "int8": np.dtype("i1"),
    "uint16": np.dtype("<u2"),
    "int16": np.dtype("<i2"),
    "uint32": np.dtype("<u4"),
    "int32": np.dtype("<i4"),
    "int64": np.dtype("<i8"),
    "float16": np.dtype("<f2"),
    "float32": np.dtype("<f4"),
    "float64": np.dtype("<f8"),
}

TOPIC_PATTERN = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]*(/[A-Za-z0-9_][A-Za-z0-9_.\-]*)*$")

#: Every reason a receiver counts a drop under (NodeStatus.drops keys); proto/envelope.yaml.
DROP_REASONS = {
    "malformed": "not [topic, header, *buffers], header not a msgpack map, or bad envelope keys",
    "topic": "topic frame is not a valid UTF-8 topic name",
    "unknown_type": "header type names no known message type",
    "version": "schema version differs from the one this receiver speaks",
    "type_mismatch": "message type does not belong on this topic",
    "field": "a scalar field is missing, of the wrong type or out of range; or an array is missing/unknown",
    "dtype": "an array has a dtype the schema does not allow",
    "shape": "an array has a shape the schema does not allow, or symbolic dims disagree",
    "bytes": "buffer count or a buffer's byte count differs from the header",
    "oversize": "header, a dimension or the total payload exceeds the schema's limits",
    "nonfinite": "a float array or field that must be finite holds NaN or Inf",
    "lost": "sequence gap on a lossless topic (dropped in transit, e.g. at a high-water mark)",
    "superseded": "older message skipped on a keep-last topic (policy, not an error)",
}


class MessageError(ValueError):
    """A message that breaks its schema. ``reason`` is one of :data:`DROP_REASONS`."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


# --- scalar fields --------------------------------------------------------------------------

SCALAR_KINDS = ("int", "float", "str", "bool", "map[str,float]", "map[str,int]")
_MISSING = object()


def _is_int(value) -> bool:
    return type(value) is int  # not bool, which msgpack keeps distinct


@dataclass(frozen=True)
class ScalarSpec:
    """One scalar header field: its kind, default (None = required), bounds, unit and meaning."""

    kind: str
    default: object = None
    required: bool = True
    min: float | None = None
    max: float | None = None
    choices: tuple[str, ...] | None = None
    finite: bool = True
    unit: str = ""
    doc: str = ""
    name: str = ""

    def __post_init__(self):
        if self.kind not in SCALAR_KINDS:
            raise ValueError(f"scalar kind {self.kind!r} is not one of {SCALAR_KINDS}")
        # The Python type a valid value has, for the one-comparison accept path in check().
        simple = {"int": int, "float": float, "str": str, "bool": bool}.get(self.kind)
        object.__setattr__(self, "_pytype", simple)

    def to_wire(self, value, where: str):
        """Coerce a Python/numpy value to its msgpack form and validate it (raises MessageError)."""
        if value.__class__ is not self._pytype:
            if isinstance(value, np.generic):
                value = value.item()
            if self.kind == "float" and _is_int(value):
                value = float(value)
            elif self.kind.startswith("map[") and isinstance(value, dict):
                value = {k: (v.item() if isinstance(v, np.generic) else v) for k, v in value.items()}
                if self.kind == "map[str,float]":
                    value = {k: float(v) if _is_int(v) else v for k, v in value.items()}
        self.check(value, where)
        return value

    def check(self, value, where: str) -> None:
        """Validate a decoded value; raises MessageError('field' | 'nonfinite')."""
        cls = value.__class__
        if cls is self._pytype:  # the common case: right type, then only bounds to check
            if cls is int:
                if (
                    MIN_INT <= value <= MAX_INT
                    and (self.min is None or value >= self.min)
                    and (self.max is None or value <= self.max)
                ):
                    return
            elif cls is float:
                if (not self.finite or math.isfinite(value)) and (
                    (self.min is None or value >= self.min)
                    and (self.max is None or value <= self.max)
                    or value != value  # NaN where allowed (finite=False) has no bounds
                ):
                    return
            elif cls is str:
                if len(value) <= MAX_STR_CHARS and (self.choices is None or value in self.choices):
                    return
            else:
                return  # bool
        self._check_slow(value, where)

    def _check_slow(self, value, where: str) -> None:
        name = f"{where}.{self.name}"
        kind = self.kind
        if kind == "int":
            if not _is_int(value):
                raise MessageError("field", f"{name} must be an int, got {type(value).__name__}")
            if not MIN_INT <= value <= MAX_INT:
                raise MessageError("field", f"{name}={value} does not fit in int64")
        elif kind == "float":
            if not isinstance(value, float):
                raise MessageError("field", f"{name} must be a float, got {type(value).__name__}")
            if not math.isfinite(value):
                if self.finite:
                    raise MessageError("nonfinite", f"{name} must be finite, got {value}")
                if value != value:
                    return
        elif kind == "str":
            if not isinstance(value, str):
                raise MessageError("field", f"{name} must be a str, got {type(value).__name__}")
            if len(value) > MAX_STR_CHARS:
                raise MessageError("field", f"{name} is longer than {MAX_STR_CHARS} characters")
            if self.choices is not None and value not in self.choices:
                raise MessageError("field", f"{name}={value!r} is not one of {list(self.choices)}")
            return
        elif kind == "bool":
            if not isinstance(value, bool):
                raise MessageError("field", f"{name} must be a bool, got {type(value).__name__}")
            return
        else:  # maps
            self._check_map(value, name)
            return
        if self.min is not None and value < self.min:
            raise MessageError("field", f"{name}={value} is below its minimum {self.min}")
        if self.max is not None and value > self.max:
            raise MessageError("field", f"{name}={value} is above its maximum {self.max}")

    def _check_map(self, value, name: str) -> None:
        if not isinstance(value, dict):
            raise MessageError("field", f"{name} must be a map, got {type(value).__name__}")
        if len(value) > MAX_MAP_ENTRIES:
            raise MessageError("field", f"{name} has more than {MAX_MAP_ENTRIES} entries")
        want_float = self.kind == "map[str,float]"
        for key, item in value.items():
            if not isinstance(key, str) or len(key) > MAX_STR_CHARS:
                raise MessageError("field", f"{name} keys must be strings, got {key!r}")
            if want_float:
                if not isinstance(item, float):
                    raise MessageError("field", f"{name}[{key!r}] must be a float, got {type(item).__name__}")
                if self.finite and not math.isfinite(item):
                    raise MessageError("nonfinite", f"{name}[{key!r}] must be finite, got {item}")
            elif not _is_int(item) or not MIN_INT <= item <= MAX_INT:
                raise MessageError("field", f"{name}[{key!r}] must be an int64, got {item!r}")

    def default_value(self):
        """A fresh copy of the default (maps are copied so instances never share one)."""
        return dict(self.default) if isinstance(self.default, dict) else self.default


# --- array fields ---------------------------------------------------------------------------

Dim = int | str


@dataclass(frozen=True)
class ArraySpec:
    """One named array: wire dtype, shape (ints are exact, strings are symbolic dims bound
    per message and limited by the message's ``dims``), whether it must be present and finite."""

    dtype: str
    shape: tuple[Dim, ...]
    required: bool = True
    finite: bool = True
    unit: str = ""
    doc: str = ""
    name: str = ""

    def __post_init__(self):
        if self.dtype not in WIRE_DTYPES:
            raise ValueError(f"dtype {self.dtype!r} is not a wire dtype {sorted(WIRE_DTYPES)}")
        # Precomputed for the codec's hot path.
        dtype = WIRE_DTYPES[self.dtype]
        fixed = self.shape if all(isinstance(d, int) for d in self.shape) else None
        object.__setattr__(self, "np_dtype", dtype)
        object.__setattr__(self, "fixed", fixed)  # the shape, when it has no symbolic dims
        object.__setattr__(self, "fixed_list", list(fixed) if fixed is not None else None)
        object.__setattr__(
            self, "fixed_nbytes", math.prod(fixed) * dtype.itemsize if fixed is not None else 0
        )
        object.__setattr__(self, "check_finite", self.finite and dtype.kind == "f")
        object.__setattr__(self, "_descs", {})

    def descriptor(self, shape: tuple[int, ...]) -> dict:
        """The header descriptor for this array at ``shape`` (cached: shapes repeat per stream)."""
        desc = self._descs.get(shape)
        if desc is None:
            if len(self._descs) >= 64:
                self._descs.clear()
            desc = self._descs[shape] = {"name": self.name, "dtype": self.dtype, "shape": list(shape)}
        return desc


@dataclass(frozen=True)
class ArraySetSpec:
    """An open set of named arrays (GaussianSnapshot): any names matching ``name_pattern``,
    one of ``dtypes``, 1..``max_ndim`` dims of at most ``max_dim`` each."""

    dtypes: tuple[str, ...]
    max_count: int
    max_ndim: int
    max_dim: int
    name_pattern: str
    finite: bool = True
    doc: str = ""
    name: str = ""

    def __post_init__(self):
        object.__setattr__(self, "_regex", re.compile(self.name_pattern))

    def name_ok(self, name: str) -> bool:
        return bool(self._regex.fullmatch(name))


@dataclass(frozen=True)
class DimSpec:
    """Bounds on a symbolic dimension (e.g. H, W, N)."""

    min: int
    max: int
    doc: str = ""


@dataclass(frozen=True)
class MessageSpec:
    """Everything the codec needs to know about one message type."""

    type: str
    version: int
    topic: str
    lane: str
    latched: bool
    max_bytes: int
    dims: dict[str, DimSpec]
    scalars: tuple[ScalarSpec, ...]
    arrays: tuple[ArraySpec, ...]
    array_set: ArraySetSpec | None = None
    doc: str = ""
    array_by_name: dict[str, ArraySpec] = field(default_factory=dict, repr=False)

    def __post_init__(self):
        self.array_by_name.update({a.name: a for a in self.arrays})
        clash = {s.name for s in self.scalars} & set(ENVELOPE_KEYS)
        if clash:
            raise ValueError(f"{self.type}: field names {sorted(clash)} are reserved envelope keys")
        for a in self.arrays:
            for d in a.shape:
                if isinstance(d, str) and d not in self.dims:
                    raise ValueError(f"{self.type}.{a.name}: symbolic dim {d!r} has no bounds in dims")
        if self.max_bytes > MAX_ARRAYS * MAX_FRAME_BYTES:
            raise ValueError(f"{self.type}: max_bytes above the envelope's limit")

    # -- array validation shared by encode and decode --------------------------------------

    def check_array(
        self, name: str, dtype_name: str, shape: tuple[int, ...], bound: dict
    ) -> ArraySpec | None:
        """Validate an array's name, dtype and shape (binding symbolic dims into ``bound``).

        Returns the fixed spec, or None for a member of the open array set.
        """
        spec = self.array_by_name.get(name)
        if spec is None:
            self._check_member(name, dtype_name, shape)
            return None
        if dtype_name != spec.dtype:
            raise MessageError("dtype", f"{self.type}.{name} must be {spec.dtype}, got {dtype_name}")
        want = spec.shape
        if shape == want:  # fixed shapes (K, R, t, poses ...) match in one comparison
            return spec
        if len(shape) != len(want):
            raise MessageError(
                "shape", f"{self.type}.{name} must have shape {_shape_text(want)}, got {list(shape)}"
            )
        for dim, got in zip(want, shape, strict=True):
            if dim.__class__ is int:
                if got != dim:
                    raise MessageError(
                        "shape", f"{self.type}.{name} must have shape {_shape_text(want)}, got {list(shape)}"
                    )
                continue
            seen = bound.get(dim)
            if seen is None:
                limits = self.dims[dim]
                if got > limits.max:
                    raise MessageError(
                        "oversize", f"{self.type}.{name}: {dim}={got} exceeds the limit {limits.max}"
                    )
                if got < limits.min:
                    raise MessageError(
                        "shape", f"{self.type}.{name}: {dim}={got} is below the minimum {limits.min}"
                    )
                bound[dim] = got
            elif seen != got:
                raise MessageError(
                    "shape", f"{self.type}.{name}: {dim}={got} disagrees with {dim}={seen} in another array"
                )
        return spec

    def _check_member(self, name: str, dtype_name: str, shape: tuple[int, ...]) -> None:
        aset = self.array_set
        where = f"{self.type}.{name}"
        if aset is None or not aset.name_ok(name):
            raise MessageError("field", f"{self.type} has no array named {name!r}")
        if dtype_name not in aset.dtypes:
            raise MessageError("dtype", f"{where} must be one of {list(aset.dtypes)}, got {dtype_name}")
        if not 1 <= len(shape) <= aset.max_ndim:
            raise MessageError("shape", f"{where} must have 1..{aset.max_ndim} dims, got {list(shape)}")
        for d in shape:
            if d > aset.max_dim:
                raise MessageError("oversize", f"{where} dim {d} exceeds {aset.max_dim}")


def _shape_text(shape) -> str:
    return "[" + ", ".join(str(d) for d in shape) + "]"


#: Arrays up to this size are checked for finiteness by a Python sum (see all_finite).
_SMALL_FINITE_BYTES = 2048


def all_finite(arr: np.ndarray) -> bool:
    """True when a real array holds no NaN/Inf (integer arrays always hold none).

    The one finiteness check of the codec, for encoding and decoding alike. Small arrays
    (K, R, t, poses... up to 2 KiB) are summed as Python floats, ~5x faster than a numpy
    call at this size: NaN and Inf propagate through a sum, and only an overflowing sum of
    huge finite values needs the exact check. Large ones are checked in chunks so the
    boolean temporary stays small."""
    if arr.nbytes <= _SMALL_FINITE_BYTES:
        if math.isfinite(sum(arr.ravel().tolist())):
            return True
        return arr.dtype.kind != "f" or bool(np.isfinite(arr).all())
    if arr.dtype.kind != "f":
        return True
    flat = arr.reshape(-1)
    step = 1 << 22
    for start in range(0, flat.size, step):
        if not np.isfinite(flat[start : start + step]).all():
            return False
    return True
