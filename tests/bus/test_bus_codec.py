"""The codec against independent truth: raw msgpack + numpy, and a table of bad inputs."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from bushelpers import assert_same_message, sample_messages

from stg_node.bus import REGISTRY, BodyPose, Frame, GaussianSnapshot, MessageError, ViewRequest
from stg_node.bus.codec import decode, decode_envelope, encode
from stg_node.bus.spec import DROP_REASONS, MAX_HEADER_BYTES, all_finite


def _encode(msg, topic=None, seq=0):
    return encode(msg, topic=topic or msg.SPEC.topic, seq=seq, src="test", stamp_ns=1_000)


@pytest.mark.parametrize("type_name", sorted(REGISTRY))
def test_round_trip_every_type(type_name):
    msg = sample_messages()[type_name]
    frames = _encode(msg, seq=42)
    back = decode(frames)
    assert_same_message(msg, back)
    assert (back.header.seq, back.header.src, back.header.stamp_ns) == (42, "test", 1_000)
    assert back.header.topic == msg.SPEC.topic


def test_wire_layout_matches_proto_read_with_plain_msgpack():
    msg = sample_messages()["Frame"]
    frames = _encode(msg, topic="rig1/camera/frame", seq=3)
    assert frames[0] == b"rig1/camera/frame"
    header = msgpack.unpackb(frames[1])
    assert {k: header[k] for k in ("type", "v", "seq", "stamp_ns", "src")} == {
        "type": "Frame",
        "v": 1,
        "seq": 3,
        "stamp_ns": 1_000,
        "src": "test",
    }
    assert (header["index"], header["time"], header["camera_id"]) == (7, 0.25, "cam0")
    names = [d["name"] for d in header["arrays"]]
    assert names == ["image", "K", "R", "t", "mask", "depth"]
    for desc, buf in zip(header["arrays"], frames[2:], strict=True):
        # Independent decode: numpy with the proto's little-endian dtype names.
        arr = np.frombuffer(memoryview(buf).tobytes(), dtype=np.dtype(desc["dtype"]).newbyteorder("<"))
        np.testing.assert_array_equal(arr.reshape(desc["shape"]), getattr(msg, desc["name"]))


def test_encode_hands_arrays_over_without_copying():
    msg = sample_messages()["Frame"]
    frames = _encode(msg)
    assert frames[2] is msg.image  # C-contiguous, right dtype: the array itself is the buffer
    assert frames[3] is msg.K


def test_decode_returns_views_of_the_received_buffers():
    msg = sample_messages()["Frame"]
    frames = [bytes(f) if isinstance(f, bytes) else bytearray(f.tobytes()) for f in _encode(msg)]
    back = decode(frames)
    assert np.shares_memory(back.image, np.frombuffer(frames[2], np.uint8))
    assert not back.image.flags.writeable


def test_non_contiguous_and_convertible_inputs_are_fixed_up():
    msg = sample_messages()["Frame"]
    wide = np.ascontiguousarray(np.transpose(msg.image, (1, 0, 2)))
    msg.image = np.transpose(wide, (1, 0, 2))  # same values, not C-contiguous
    msg.K = msg.K.astype(np.float32).tolist()  # a list of float32 values -> float64
    back = decode(_encode(msg))
    np.testing.assert_array_equal(back.image, msg.image)
    np.testing.assert_allclose(back.K, np.asarray(msg.K), rtol=1e-6)


@pytest.mark.parametrize(
    "change, reason, needle",
    [
        (lambda m: setattr(m, "K", np.eye(4)), "shape", "Frame.K"),
        (lambda m: setattr(m, "image", m.image.astype(np.float32)), "dtype", "Frame.image"),
        (lambda m: setattr(m, "mask", np.zeros((3, 3), np.uint8)), "shape", "H=3"),
        (lambda m: setattr(m, "R", np.full((3, 3), np.nan)), "nonfinite", "Frame.R"),
        (lambda m: setattr(m, "index", -1), "field", "Frame.index"),
        (lambda m: setattr(m, "index", "7"), "field", "Frame.index"),
        (lambda m: setattr(m, "camera_id", 3), "field", "Frame.camera_id"),
        (lambda m: setattr(m, "time", float("inf")), "nonfinite", "Frame.time"),
        (lambda m: setattr(m, "image", np.zeros((5000, 2, 3), np.uint8)), "oversize", "H=5000"),
    ],
)
def test_encode_rejects_a_broken_message_naming_the_field(change, reason, needle):
    msg = sample_messages()["Frame"]
    change(msg)
    with pytest.raises(MessageError) as info:
        _encode(msg)
    assert info.value.reason == reason
    assert needle in str(info.value)


def test_cross_field_rules():
    view = sample_messages()["ViewRequest"]
    view.poses = None
    with pytest.raises(MessageError, match="poses is required"):
        _encode(view)
    view.follow_live = True
    view.near, view.far = 5.0, 1.0
    with pytest.raises(MessageError, match="far"):
        _encode(view)


def test_nan_allowed_only_where_the_schema_says():
    metrics = sample_messages()["TrainerMetrics"]  # loss=NaN: allowed
    assert math.isnan(decode(_encode(metrics)).loss)
    metrics.it_per_s = float("nan")
    with pytest.raises(MessageError) as info:
        _encode(metrics)
    assert info.value.reason == "nonfinite"


def test_unknown_header_keys_are_ignored_for_forward_compatibility():
    frames = _encode(sample_messages()["BodyPose"])
    header = msgpack.unpackb(frames[1])
    header["added_in_a_later_minor"] = 1.5
    frames[1] = msgpack.packb(header)
    assert isinstance(decode(frames), BodyPose)


# --- bad input: each is a MessageError with the drop reason proto/envelope.yaml lists -------------


def _frame_msg():
    return sample_messages()["Frame"]


def _with_header(frames, **changes):
    header = msgpack.unpackb(frames[1])
    for key, value in changes.items():
        if value is _DELETE:
            header.pop(key)
        else:
            header[key] = value
    return [frames[0], msgpack.packb(header), *frames[2:]]


def _desc(frames, index, **changes):
    header = msgpack.unpackb(frames[1])
    header["arrays"][index].update(changes)
    return [frames[0], msgpack.packb(header), *frames[2:]]


_DELETE = object()


def _bad_cases():
    good = _encode(_frame_msg())
    pose = _encode(sample_messages()["BodyPose"])
    return {
        "one frame": ([good[0]], "malformed"),
        "not msgpack": ([good[0], b"\xc1\xc1", *good[2:]], "malformed"),
        "trailing bytes": ([good[0], good[1] + b"\x00", *good[2:]], "malformed"),
        "header is a list": ([good[0], msgpack.packb([1, 2]), *good[2:]], "malformed"),
        "int map keys": ([good[0], msgpack.packb({1: 2}), *good[2:]], "malformed"),
        "no type": (_with_header(good, type=_DELETE), "malformed"),
        "negative seq": (_with_header(good, seq=-1), "malformed"),
        "bool seq": (_with_header(good, seq=True), "malformed"),
        "src not a string": (_with_header(good, src=b"bytes"), "malformed"),
        "arrays not a list": (_with_header(good, arrays={}), "malformed"),
        "unknown type": (_with_header(good, type="Teapot"), "unknown_type"),
        "wrong version": (_with_header(good, v=2), "version"),
        "Frame on body/pose": ([b"body/pose", *good[1:]], "type_mismatch"),
        "pose on rig1/camera/frame": ([b"rig1/camera/frame", *pose[1:]], "type_mismatch"),
        "topic not utf-8": ([b"\xff\xfe", *good[1:]], "topic"),
        "topic with spaces": ([b"camera frame", *good[1:]], "topic"),
        "K float32": (_desc(good, 1, dtype="float32"), "dtype"),
        "unknown dtype": (_desc(good, 1, dtype="complex64"), "dtype"),
        "K 4x4": (_desc(good, 1, shape=[4, 4]), "shape"),
        "negative dim": (_desc(good, 0, shape=[-6, 8, 3]), "shape"),
        "float dim": (_desc(good, 0, shape=[6.0, 8, 3]), "shape"),
        "mask H disagrees": (_desc(good, 4, shape=[5, 8]), "shape"),
        "image too tall": (_desc(good, 0, shape=[5000, 8, 3]), "oversize"),
        "claims 2 GiB": (_desc(good, 0, shape=[65536, 32768]), "oversize"),
        "buffer short": ([*good[:2], memoryview(good[2]).tobytes()[:-1], *good[3:]], "bytes"),
        "buffer long": ([*good[:2], memoryview(good[2]).tobytes() + b"x", *good[3:]], "bytes"),
        "extra buffer": ([*good, b"x"], "bytes"),
        "missing buffer": (good[:-1], "bytes"),
        "header too big": (_with_header(good, camera_id="x" * MAX_HEADER_BYTES), "oversize"),
        "NaN in R": ([*good[:3], good[3], np.full((3, 3), np.nan), *good[5:]], "nonfinite"),
        "index a string": (_with_header(good, index="7"), "field"),
        "index a bool": (_with_header(good, index=True), "field"),
        "index missing": (_with_header(good, index=_DELETE), "field"),
        "confidence 2": (_with_header(pose, confidence=2.0), "field"),
        "unknown array": (_desc(good, 4, name="bogus"), "field"),
        "duplicate array": (_desc(good, 3, name="R", shape=[3, 3]), "field"),
        "missing required array": (
            [
                good[0],
                msgpack.packb({**msgpack.unpackb(good[1]), "arrays": msgpack.unpackb(good[1])["arrays"][1:]}),
                *good[3:],
            ],
            "field",
        ),
    }


@pytest.mark.parametrize("case", sorted(_bad_cases()))
def test_decode_rejects_bad_input_with_its_drop_reason(case):
    frames, reason = _bad_cases()[case]
    with pytest.raises(MessageError) as info:
        decode(frames)
    assert info.value.reason == reason, str(info.value)
    assert reason in DROP_REASONS


def test_duplicate_array_names_are_rejected():
    good = _encode(_frame_msg())
    header = msgpack.unpackb(good[1])
    header["arrays"][2] = dict(header["arrays"][1])  # R described as a second K
    with pytest.raises(MessageError) as info:
        decode([good[0], msgpack.packb(header), *good[2:]])
    assert info.value.reason == "field" and "twice" in str(info.value)


def test_snapshot_array_set_limits():
    snap = sample_messages()["GaussianSnapshot"]
    good = _encode(snap)
    bad_dtype = _desc(good, 0, dtype="int32")
    with pytest.raises(MessageError) as info:
        decode(bad_dtype)
    assert info.value.reason == "dtype"
    snap.arrays["bad name!"] = np.zeros(3, np.float32)
    with pytest.raises(MessageError) as info:
        _encode(snap)
    assert info.value.reason == "field"


def test_envelope_decoding_accepts_any_type_but_checks_byte_counts():
    good = _encode(_frame_msg())
    env = decode_envelope(_with_header(good, type="SomethingNew", v=9))
    assert env.type == "SomethingNew" and env.arrays["image"].shape == (6, 8, 3)
    with pytest.raises(MessageError) as info:
        decode_envelope([*good[:2], b"short", *good[3:]])
    assert info.value.reason == "bytes"


def test_all_finite_agrees_with_numpy_on_small_and_large_arrays():
    rng = np.random.default_rng(1)
    for size in (1, 9, 256, 257, 5000):
        arr = rng.normal(size=size)
        assert all_finite(arr)
        for bad in (np.nan, np.inf, -np.inf):
            broken = arr.copy()
            broken[rng.integers(size)] = bad
            assert not all_finite(broken)
    huge = np.full(10, 1e308)  # a finite array whose sum overflows
    assert all_finite(huge) == bool(np.isfinite(huge).all())


# --- fuzzing ------------------------------------------------------------------------------------------


def _random_msgpack_value(rng, depth=0):
    kind = rng.integers(9 if depth < 3 else 6)
    if kind == 0:
        return int(rng.integers(-(2**62), 2**62))
    if kind == 1:
        return float(rng.choice([rng.normal(), np.nan, np.inf, -1e300]))
    if kind == 2:
        return "".join(chr(int(c)) for c in rng.integers(32, 0x2FF, rng.integers(0, 12)))
    if kind == 3:
        return bytes(rng.integers(0, 256, rng.integers(0, 12), dtype=np.uint8))
    if kind == 4:
        return bool(rng.integers(2))
    if kind == 5:
        return None
    if kind == 6:
        return [_random_msgpack_value(rng, depth + 1) for _ in range(rng.integers(0, 4))]
    if kind == 7:
        keys = ["type", "v", "seq", "stamp_ns", "src", "arrays", "name", "dtype", "shape", "index", "x"]
        return {
            str(rng.choice(keys)): _random_msgpack_value(rng, depth + 1) for _ in range(rng.integers(0, 5))
        }
    return msgpack.ExtType(int(rng.integers(0, 127)), b"abc")


def _mutate(rng, frames):
    frames = [memoryview(f).tobytes() if not isinstance(f, bytes) else f for f in frames]
    if len(frames) < 2:
        return frames + [b"\x80"]
    try:
        return _mutate_structured(rng, frames)
    except Exception:  # an earlier mutation broke the structure: flip bytes instead
        header = bytearray(frames[1] or b"\x80")
        header[rng.integers(len(header))] = rng.integers(256)
        return [frames[0], bytes(header), *frames[2:]]


def _mutate_structured(rng, frames):
    op = rng.integers(8)
    if op == 0:  # flip bytes in the header
        header = bytearray(frames[1] or b"\x80")
        for _ in range(rng.integers(1, 4)):
            header[rng.integers(len(header))] = rng.integers(256)
        frames[1] = bytes(header)
    elif op == 1:  # truncate or extend a buffer
        i = int(rng.integers(1, len(frames)))
        frames[i] = (
            frames[i][: rng.integers(len(frames[i]) + 1)] if rng.integers(2) else frames[i] + b"\0" * 3
        )
    elif op == 2:  # replace a header value with anything
        header = msgpack.unpackb(frames[1])
        header[str(rng.choice(list(header)))] = _random_msgpack_value(rng)
        frames[1] = msgpack.packb(header)
    elif op == 3:  # corrupt an array descriptor
        header = msgpack.unpackb(frames[1])
        if header["arrays"]:
            desc = header["arrays"][rng.integers(len(header["arrays"]))]
            desc[str(rng.choice(["name", "dtype", "shape"]))] = _random_msgpack_value(rng)
        frames[1] = msgpack.packb(header)
    elif op == 4:  # random shapes
        header = msgpack.unpackb(frames[1])
        if header["arrays"]:
            desc = header["arrays"][rng.integers(len(header["arrays"]))]
            desc["shape"] = [int(d) for d in rng.integers(-2, 5000, rng.integers(0, 5))]
        frames[1] = msgpack.packb(header)
    elif op == 5:  # drop or duplicate frames
        i = int(rng.integers(len(frames)))
        frames = frames[:i] + frames[i + 1 :] if rng.integers(2) else frames[: i + 1] + frames[i:]
    elif op == 6:  # a random header altogether
        frames[1] = msgpack.packb(_random_msgpack_value(rng))
    else:  # random topic bytes
        frames[0] = bytes(rng.integers(0, 256, rng.integers(0, 40), dtype=np.uint8))
    return frames


def test_fuzz_decoder_never_raises_anything_but_message_error():
    """12,000 random and mutated messages: every one decodes or is a MessageError with a known reason."""
    rng = np.random.default_rng(20261121)
    seeds = [_encode(m) for m in sample_messages().values()]
    outcomes: dict[str, int] = {}
    for i in range(12_000):
        if i % 4 == 0:
            frames = [
                bytes(rng.integers(0, 256, rng.integers(0, 64), dtype=np.uint8))
                for _ in range(rng.integers(0, 6))
            ]
        else:
            frames = seeds[rng.integers(len(seeds))]
            for _ in range(rng.integers(1, 3)):
                frames = _mutate(rng, frames)
        for fn in (decode, decode_envelope):
            try:
                result = fn(frames)
            except MessageError as exc:
                assert exc.reason in DROP_REASONS
                outcomes[exc.reason] = outcomes.get(exc.reason, 0) + 1
                continue
            outcomes["ok"] = outcomes.get("ok", 0) + 1
            arrays = result.arrays if fn is decode_envelope else {}
            for arr in arrays.values():
                assert arr.nbytes == int(np.prod(arr.shape)) * arr.itemsize
    # The fuzzer must reach deep: valid messages survive and many different checks fire.
    assert outcomes.get("ok", 0) > 100
    assert len(set(outcomes) - {"ok"}) >= 8, outcomes


def test_messages_of_each_type_are_registered_once():
    assert set(REGISTRY) == {
        "Frame",
        "BodyPose",
        "GaussianSnapshot",
        "ViewRequest",
        "RenderedImage",
        "TrainerMetrics",
        "NodeStatus",
        "Ack",
    }
    assert REGISTRY["Frame"] is Frame and REGISTRY["GaussianSnapshot"] is GaussianSnapshot
    assert ViewRequest.SPEC.lane == "reliable"


def test_layout_cache_never_admits_what_the_checks_refuse():
    """Once a layout is cached, descriptors equal to it under == (6.0 == 6, True == 1) must
    still be refused: validation may not depend on what arrived before."""
    good = _encode(_frame_msg())
    decode(good)  # caches the layout
    for bad_dim in (6.0, True):
        header = msgpack.unpackb(good[1])
        header["arrays"][0]["shape"][0] = bad_dim
        with pytest.raises(MessageError) as info:
            decode([good[0], msgpack.packb(header), *good[2:]])
        assert info.value.reason == "shape"
    assert isinstance(decode(good), Frame)
