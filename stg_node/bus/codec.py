"""The wire codec: typed messages <-> ZeroMQ multipart ``[topic, header, *buffers]``.

Encoding validates a message against its schema (a node's bug raises at publish time,
naming the field) and returns the frames with the arrays themselves as buffers, ready for
``send_multipart(frames, copy=False)``: nothing is copied unless an array is not
C-contiguous or needs a dtype conversion.

Decoding checks, in this order and before it trusts anything: frame layout, topic, header
size, msgpack, envelope keys, type, version, topic/type agreement, each array descriptor
(dtype, shape and symbolic dims, size limits) against its buffer's byte count, finiteness,
then the scalar fields. Only then are arrays created, as read-only ``np.frombuffer`` views
of the received frames (zero-copy). Every failure is a :class:`MessageError` whose
``reason`` is the drop-counter key (spec.DROP_REASONS).
"""

from __future__ import annotations

from dataclasses import dataclass

import msgpack
import numpy as np

from stg_node.bus.messages import REGISTRY, TOPIC_TYPES, Header, Message
from stg_node.bus.spec import (
    MAX_ARRAYS,
    MAX_FRAME_BYTES,
    MAX_HEADER_BYTES,
    MAX_INT,
    MAX_NDIM,
    MAX_SRC_CHARS,
    MAX_TOPIC_BYTES,
    TOPIC_PATTERN,
    WIRE_DTYPES,
    MessageError,
    MessageSpec,
    all_finite,
)
from stg_node.bus.topics import base_name
from stg_node.safe_load import unpack_msgpack

_WIRE_NAME = {dt.str: name for name, dt in WIRE_DTYPES.items()}
_MISSING = object()


@dataclass(slots=True)
class Envelope:
    """A message checked at the envelope level only (any type): what tools and recorders see."""

    topic: str
    header: dict
    arrays: dict[str, np.ndarray]
    nbytes: int  # payload: header + buffers (what NodeStatus and stg-topic bw count)
    frames: list | None = None  # as received, [topic, header, *buffers]: the exact bytes (recorders)

    @property
    def type(self) -> str:
        return self.header["type"]


# --- encode ------------------------------------------------------------------------------------


def _as_wire_array(value, dtype: np.dtype | None, where: str) -> np.ndarray:
    """The array as a C-contiguous little-endian buffer of ``dtype``; no copy when it already is."""
    arr = value if isinstance(value, np.ndarray) else np.asarray(value)
    if dtype is None:
        return np.ascontiguousarray(arr)
    if arr.dtype != dtype:
        if not np.can_cast(arr.dtype, dtype, casting="same_kind"):
            raise MessageError(
                "dtype", f"{where} must be {dtype.name}, got {arr.dtype} (not safely castable)"
            )
        arr = arr.astype(dtype)
    return np.ascontiguousarray(arr)


def encode(msg: Message, *, topic: str, seq: int, src: str, stamp_ns: int) -> list:
    """Validate ``msg`` and return ``[topic, header, *buffers]`` for send_multipart(copy=False)."""
    return encode_counted(msg, topic=topic, seq=seq, src=src, stamp_ns=stamp_ns)[0]


def encode_counted(msg: Message, *, topic: str, seq: int, src: str, stamp_ns: int) -> tuple[list, int]:
    """:func:`encode`, plus the payload size (header + buffers) in bytes."""
    spec: MessageSpec = msg.SPEC
    where = spec.type
    header = {"type": spec.type, "v": spec.version, "seq": seq, "stamp_ns": stamp_ns, "src": src}
    for s in spec.scalars:
        header[s.name] = s.to_wire(getattr(msg, s.name), where)
    descs: list = []
    buffers: list[np.ndarray] = []
    bound: dict[str, int] = {}
    total = 0
    fields = msg.__dict__
    for a in spec.arrays:
        value = fields[a.name]
        if value is None:
            if a.required:
                raise MessageError("field", f"{where}.{a.name} is required")
            continue
        if value.__class__ is np.ndarray and value.dtype == a.np_dtype:
            arr = np.ascontiguousarray(value)  # the same object when already contiguous
        else:
            arr = _as_wire_array(value, a.np_dtype, f"{where}.{a.name}")
        shape = arr.shape
        if shape != a.fixed:
            spec.check_array(a.name, a.dtype, shape, bound)
        if a.check_finite and not all_finite(arr):
            raise MessageError("nonfinite", f"{where}.{a.name} holds NaN or Inf")
        total += arr.nbytes
        descs.append(a.descriptor(shape))
        buffers.append(arr)
    aset = spec.array_set
    if aset is not None:
        members = getattr(msg, aset.name)
        if len(members) > aset.max_count:
            raise MessageError(
                "oversize", f"{where}.{aset.name} has {len(members)} arrays, limit {aset.max_count}"
            )
        for name, value in members.items():
            arr = _as_wire_array(value, None, f"{where}.{name}")
            if not isinstance(name, str):
                raise MessageError("field", f"{where}.{aset.name} keys must be strings, got {name!r}")
            dtype_name = _WIRE_NAME.get(arr.dtype.str)
            if dtype_name not in aset.dtypes:
                raise MessageError(
                    "dtype", f"{where}.{name} must be one of {list(aset.dtypes)}, got {arr.dtype}"
                )
            spec.check_array(name, dtype_name, arr.shape, bound)
            if aset.finite and not all_finite(arr):
                raise MessageError("nonfinite", f"{where}.{name} holds NaN or Inf")
            total += arr.nbytes
            descs.append({"name": name, "dtype": dtype_name, "shape": list(arr.shape)})
            buffers.append(arr)
    if total > spec.max_bytes:
        raise MessageError("oversize", f"{where} carries {total} bytes of arrays, limit {spec.max_bytes}")
    if total > MAX_FRAME_BYTES and any(b.nbytes > MAX_FRAME_BYTES for b in buffers):
        raise MessageError("oversize", f"{where} has an array above {MAX_FRAME_BYTES} bytes")
    msg.check()
    header["arrays"] = descs
    packed = msgpack.packb(header, use_bin_type=True)
    if len(packed) > MAX_HEADER_BYTES:
        raise MessageError("oversize", f"{where} header is {len(packed)} bytes, limit {MAX_HEADER_BYTES}")
    return [topic.encode(), packed, *buffers], len(packed) + total


# --- decode ------------------------------------------------------------------------------------


_unpackb = unpack_msgpack  # msgpack.unpackb refusing extension types
_topic_cache: dict[bytes, str] = {}


def _topic(frame) -> str:
    raw = bytes(frame)
    topic = _topic_cache.get(raw)
    if topic is not None:
        return topic
    if len(raw) > MAX_TOPIC_BYTES:
        raise MessageError("topic", f"topic frame of {len(raw)} bytes exceeds {MAX_TOPIC_BYTES}")
    try:
        topic = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise MessageError("topic", "topic frame is not UTF-8") from None
    if not TOPIC_PATTERN.match(topic):
        raise MessageError("topic", f"topic {topic!r} is not a valid topic name")
    if len(_topic_cache) >= 4096:  # bounded: a peer inventing topics cannot grow it
        _topic_cache.clear()
    _topic_cache[raw] = topic
    return topic


def _header(frames) -> tuple[str, dict]:
    n = len(frames)
    if n < 2:
        raise MessageError("malformed", f"expected frames [topic, header, *buffers], got {n} frame(s)")
    topic = _topic(frames[0])
    raw = frames[1]
    size = raw.nbytes if raw.__class__ is memoryview else len(raw)
    if size > MAX_HEADER_BYTES:
        raise MessageError("oversize", f"header of {size} bytes exceeds {MAX_HEADER_BYTES}")
    try:
        # msgpack >= 1.0 defaults: raw=False (str stays str), strict_map_key=True (str/bytes keys).
        header = _unpackb(raw)
    except Exception as exc:  # msgpack raises a zoo of types (ExtraData, StackError, ValueError...)
        raise MessageError("malformed", f"header is not valid msgpack ({type(exc).__name__})") from None
    if type(header) is not dict:
        raise MessageError("malformed", f"header must be a msgpack map, got {type(header).__name__}")
    get = header.get
    if type(get("type")) is not str:
        raise MessageError("malformed", "header has no string 'type'")
    if type(get("v")) is not int:
        raise MessageError("malformed", "header has no integer 'v'")
    seq = get("seq")
    if type(seq) is not int or not 0 <= seq <= MAX_INT:
        raise MessageError("malformed", f"header 'seq' must be an int >= 0, got {seq!r}")
    stamp = get("stamp_ns")
    if type(stamp) is not int or not 0 <= stamp <= MAX_INT:
        raise MessageError("malformed", f"header 'stamp_ns' must be an int >= 0, got {stamp!r}")
    src = get("src")
    if type(src) is not str or len(src) > MAX_SRC_CHARS:
        raise MessageError("malformed", f"header 'src' must be a string of <= {MAX_SRC_CHARS} characters")
    descs = get("arrays")
    if type(descs) is not list:
        raise MessageError("malformed", "header 'arrays' must be a list")
    if len(descs) > MAX_ARRAYS:
        raise MessageError("oversize", f"{len(descs)} arrays exceed the limit {MAX_ARRAYS}")
    if len(descs) != n - 2:
        raise MessageError("bytes", f"header describes {len(descs)} arrays but {n - 2} buffers follow")
    return topic, header


def _descriptor(desc, index: int) -> tuple[str, str, tuple[int, ...], int]:
    """name, dtype name, shape and byte count of one array descriptor, checked generically."""
    if type(desc) is not dict:
        raise MessageError("malformed", f"array descriptor {index} is not a map")
    name, dtype_name, shape = desc.get("name"), desc.get("dtype"), desc.get("shape")
    if type(name) is not str or not name or len(name) > 128:
        raise MessageError("malformed", f"array descriptor {index} has no valid 'name'")
    dtype = WIRE_DTYPES.get(dtype_name) if type(dtype_name) is str else None
    if dtype is None:
        raise MessageError(
            "dtype", f"array {name!r}: dtype {dtype_name!r} is not one of {sorted(WIRE_DTYPES)}"
        )
    if type(shape) is not list or len(shape) > MAX_NDIM:
        raise MessageError(
            "shape", f"array {name!r}: shape must be a list of <= {MAX_NDIM} ints, got {shape!r}"
        )
    count = 1
    for d in shape:
        if type(d) is not int or d < 0:
            raise MessageError("shape", f"array {name!r}: shape must hold ints >= 0, got {shape!r}")
        count *= d
    nbytes = count * dtype.itemsize
    if nbytes > MAX_FRAME_BYTES:
        raise MessageError("oversize", f"array {name!r} of {nbytes} bytes exceeds {MAX_FRAME_BYTES}")
    return name, dtype_name, tuple(shape), nbytes


def _view(frame, dtype_name: str, shape: tuple[int, ...], nbytes: int, name: str) -> np.ndarray:
    buf = memoryview(frame)
    if buf.nbytes != nbytes:
        raise MessageError("bytes", f"array {name!r}: buffer has {buf.nbytes} bytes, header implies {nbytes}")
    return np.frombuffer(buf.toreadonly(), dtype=WIRE_DTYPES[dtype_name]).reshape(shape)


def decode_envelope(frames) -> Envelope:
    """Check the envelope (layout, header, descriptors vs byte counts) of a message of any type."""
    topic, header = _header(frames)
    arrays = {}
    total = 0
    for index, (desc, frame) in enumerate(zip(header["arrays"], frames[2:], strict=True)):
        name, dtype_name, shape, nbytes = _descriptor(desc, index)
        if name in arrays:
            raise MessageError("field", f"array {name!r} appears twice")
        arrays[name] = _view(frame, dtype_name, shape, nbytes, name)
        total += nbytes
    header_bytes = memoryview(frames[1]).nbytes
    return Envelope(topic=topic, header=header, arrays=arrays, nbytes=header_bytes + total, frames=frames)


_expected_cache: dict[str, type[Message] | None] = {}


def expected_type(topic: str) -> type[Message] | None:
    """The message class a standard topic (with any namespace) must carry; None for custom topics."""
    try:
        return _expected_cache[topic]
    except KeyError:
        pass
    base = base_name(topic, TOPIC_TYPES)
    cls = TOPIC_TYPES[base] if base else None
    if len(_expected_cache) >= 4096:
        _expected_cache.clear()
    _expected_cache[topic] = cls
    return cls


_layouts: dict[str, list] = {}  # type -> [(descriptors, layout)], the few layouts streams repeat
_MAX_LAYOUTS = 8


def _layout(spec: MessageSpec, descs: list) -> tuple[tuple, tuple]:
    """The checked layout of a message's arrays: ((name, dtype, shape, nbytes, check_finite,
    fixed_field), ...) and the optional arrays it lacks.

    A stream repeats the same descriptors message after message, so a layout that passed
    once is cached per type and found again by comparing descriptor lists (one C-level ==).
    == alone would let 6.0 or True stand in for the dim 6 or 1, so a hit also requires every
    dim to be a real int: the cache never admits what the checks would refuse.
    """
    cache = _layouts.setdefault(spec.type, [])
    for known, layout in cache:
        if known == descs:
            for desc in descs:
                for dim in desc["shape"]:
                    if dim.__class__ is not int:
                        return _check_layout(spec, descs)  # raises: a dim that is not an int
            return layout
    layout = _check_layout(spec, descs)
    cache.append((descs, layout))
    if len(cache) > _MAX_LAYOUTS:
        cache.pop(0)
    return layout


def _check_layout(spec: MessageSpec, descs: list) -> tuple[tuple, tuple]:
    entries = []
    bound: dict[str, int] = {}
    fields: set[str] = set()
    members: set[str] = set()
    total = 0
    for index, desc in enumerate(descs):
        name, dtype_name, shape, nbytes = _descriptor(desc, index)
        aspec = spec.check_array(name, dtype_name, shape, bound)
        total += nbytes
        if total > spec.max_bytes:
            raise MessageError("oversize", f"{spec.type} arrays exceed {spec.max_bytes} bytes")
        seen = fields if aspec is not None else members
        if name in seen:
            raise MessageError("field", f"{spec.type}.{name} appears twice")
        seen.add(name)
        finite = aspec.check_finite if aspec is not None else spec.array_set.finite
        entries.append((name, WIRE_DTYPES[dtype_name], shape, nbytes, finite, aspec is not None))
    for a in spec.arrays:
        if a.required and a.name not in fields:
            raise MessageError("field", f"{spec.type}.{a.name} is required but missing")
    if spec.array_set is not None and len(members) > spec.array_set.max_count:
        raise MessageError(
            "oversize", f"{spec.type} has {len(members)} arrays, limit {spec.array_set.max_count}"
        )
    absent = tuple(a.name for a in spec.arrays if a.name not in fields)
    return tuple(entries), absent


def decode(frames) -> Message:
    """Validate and decode ``[topic, header, *buffers]`` into its typed message (zero-copy arrays)."""
    topic, header = _header(frames)
    type_name = header["type"]
    cls = REGISTRY.get(type_name)
    if cls is None:
        raise MessageError("unknown_type", f"unknown message type {type_name[:64]!r}")
    spec: MessageSpec = cls.SPEC
    if header["v"] != spec.version:
        raise MessageError(
            "version", f"{type_name} v{header['v']} received, this node speaks v{spec.version}"
        )
    want = expected_type(topic)
    if want is not None and want is not cls:
        raise MessageError("type_mismatch", f"{type_name} on topic {topic!r}, which carries {want.SPEC.type}")

    entries, absent = _layout(spec, header["arrays"])
    kwargs: dict = {}
    members: dict[str, np.ndarray] = {}
    for index, (name, dtype, shape, nbytes, finite, fixed) in enumerate(entries):
        # Read-only view of the frame: shared with it (and, over inproc, with the sender).
        buf = memoryview(frames[index + 2]).toreadonly()
        if buf.nbytes != nbytes:
            raise MessageError(
                "bytes", f"array {name!r}: buffer has {buf.nbytes} bytes, header implies {nbytes}"
            )
        flat = np.frombuffer(buf, dtype=dtype)
        if finite and not all_finite(flat):
            raise MessageError("nonfinite", f"{type_name}.{name} holds NaN or Inf")
        (kwargs if fixed else members)[name] = flat.reshape(shape)
    for name in absent:
        kwargs[name] = None
    if spec.array_set is not None:
        kwargs[spec.array_set.name] = members
    for s in spec.scalars:
        value = header.get(s.name, _MISSING)
        if value is _MISSING:
            if s.required:
                raise MessageError("field", f"{type_name}.{s.name} is required but missing")
            value = s.default_value()
        else:
            s.check(value, type_name)
        kwargs[s.name] = value
    # Every field is in kwargs: fill the instance directly (a dataclass __init__ costs more).
    msg = object.__new__(cls)
    kwargs["header"] = Header(header["stamp_ns"], header["seq"], header["src"], topic)
    msg.__dict__.update(kwargs)
    msg.check()
    return msg
