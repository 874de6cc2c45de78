"""proto/ and the Python message classes never drift: every field, dtype, shape, unit, limit."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import yaml

from stg_node.bus import REGISTRY
from stg_node.bus.broker import LATCHED_TOPICS
from stg_node.bus.messages import TOPIC_TYPES
from stg_node.bus.schema import differences, load_proto
from stg_node.bus.spec import (
    DROP_REASONS,
    ENVELOPE_KEYS,
    ENVELOPE_VERSION,
    MAX_ARRAYS,
    MAX_FRAME_BYTES,
    MAX_HEADER_BYTES,
    MAX_MAP_ENTRIES,
    MAX_NDIM,
    MAX_SRC_CHARS,
    MAX_STR_CHARS,
    MAX_TOPIC_BYTES,
    SCALAR_KINDS,
    WIRE_DTYPES,
)
from stg_node.bus.topics import LANES

PROTO = Path(__file__).resolve().parents[2] / "proto"


@pytest.fixture(scope="module")
def proto():
    return load_proto(PROTO)


@pytest.fixture(scope="module")
def envelope():
    return yaml.safe_load((PROTO / "envelope.yaml").read_text())


@pytest.mark.parametrize("type_name", sorted(REGISTRY))
def test_class_matches_its_proto_file(proto, type_name):
    assert type_name in proto, f"proto/ has no schema for {type_name}"
    assert differences(REGISTRY[type_name], proto[type_name]) == []
    assert proto[type_name]["_file"] == f"{type_name.lower()}.yaml"


def test_every_proto_file_has_a_class(proto):
    assert set(proto) == set(REGISTRY)


@pytest.mark.parametrize(
    "path, value",
    [
        (("arrays", "K", "dtype"), "float32"),
        (("arrays", "image", "shape"), ["H", "W", 4]),
        (("fields", "index", "unit"), "s"),
        (("fields", "time", "default"), 1.0),
        (("version",), 2),
        (("limits", "dims", "H", "max"), 8192),
        (("arrays", "mask", "required"), True),
    ],
)
def test_the_comparison_notices_drift(proto, path, value):
    """Guard against a test that cannot fail: any edit of the schema is reported."""
    edited = copy.deepcopy(proto["Frame"])
    node = edited
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    assert differences(REGISTRY["Frame"], edited), path


def test_missing_descriptions_are_reported(proto):
    edited = copy.deepcopy(proto["BodyPose"])
    edited["fields"]["confidence"]["description"] = ""
    assert any("description" in p for p in differences(REGISTRY["BodyPose"], edited))


def test_envelope_matches_the_codec(envelope):
    assert envelope["envelope_version"] == ENVELOPE_VERSION
    assert tuple(envelope["header"]) == ENVELOPE_KEYS
    assert list(envelope["array_descriptor"]) == ["name", "dtype", "shape"]
    assert envelope["dtypes"] == {name: dt.itemsize for name, dt in WIRE_DTYPES.items()}
    assert all(dt.byteorder in "<|=" for dt in WIRE_DTYPES.values())
    assert set(envelope["scalar_types"]) == set(SCALAR_KINDS)
    assert envelope["limits"] == {
        "max_topic_bytes": MAX_TOPIC_BYTES,
        "max_header_bytes": MAX_HEADER_BYTES,
        "max_src_chars": MAX_SRC_CHARS,
        "max_arrays": MAX_ARRAYS,
        "max_ndim": MAX_NDIM,
        "max_frame_bytes": MAX_FRAME_BYTES,
        "max_str_chars": MAX_STR_CHARS,
        "max_map_entries": MAX_MAP_ENTRIES,
    }
    assert envelope["drop_reasons"] == DROP_REASONS


def test_envelope_topics_lanes_and_latching_match(envelope):
    assert envelope["topics"]["standard"] == {topic: cls.SPEC.type for topic, cls in TOPIC_TYPES.items()}
    assert set(envelope["latched_topics"]) == set(LATCHED_TOPICS)
    assert set(envelope["lanes"]) == set(LANES)
    for name, lane in LANES.items():
        entry = envelope["lanes"][name]
        assert (entry["index"], entry["hwm"], entry["keep_last"]) == (lane.index, lane.hwm, lane.keep_last)
        assert set(entry["topics"]) == {t for t, cls in TOPIC_TYPES.items() if cls.SPEC.lane == name}
