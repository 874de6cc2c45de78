"""BusConfig is truly immutable: no attribute or lane can change after construction, so one config
can be shared by a node's publisher, subscribers and threads."""

from __future__ import annotations

import copy
import dataclasses
import pickle

import pytest

from stg_node.bus import BusConfig
from stg_node.bus.config import as_config


def test_fields_cannot_be_reassigned():
    config = BusConfig(url="ipc:///tmp/stg-test/bus", namespace="rig1")
    for name, value in [("url", "tcp://x:1"), ("namespace", "rig2"), ("keys", "k"), ("lanes", {})]:
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(config, name, value)
    assert config.url == "ipc:///tmp/stg-test/bus" and config.namespace == "rig1"


def test_lanes_are_a_read_only_copy_of_what_was_passed():
    overrides = {"camera/frame": "reliable"}
    config = BusConfig(url="ipc:///tmp/stg-test/bus", lanes=overrides)
    overrides["camera/frame"] = "bulk"  # the caller's dict changes afterwards: the config does not
    with pytest.raises(TypeError):
        config.lanes["camera/frame"] = "bulk"
    assert config.lane_of("camera/frame").name == "reliable"
    assert config.lane_of("rig1/camera/frame").name == "reliable"


def test_variants_are_new_checked_configs():
    config = BusConfig(url="ipc:///tmp/stg-test/bus")
    moved = config.with_(lanes={"camera/frame": "reliable"})
    assert config.lane_of("camera/frame").name == "latest"
    assert moved.lane_of("camera/frame").name == "reliable"
    with pytest.raises(ValueError, match="lane 'fast'"):
        config.with_(lanes={"camera/frame": "fast"})
    with pytest.raises(ValueError, match="too long"):
        config.with_(url="ipc:///tmp/" + "x" * 120)  # checked at construction, not at the first bind


def test_equal_configs_hash_alike_and_survive_pickle_and_copy():
    a = BusConfig(url="tcp://127.0.0.1:7400", keys="keys", key_name="robot", lanes={"x/y": "bulk"})
    b = BusConfig(url="tcp://127.0.0.1:7400", keys="keys", key_name="robot", lanes={"x/y": "bulk"})
    assert a == b and hash(a) == hash(b) and len({a, b}) == 1
    for clone in (pickle.loads(pickle.dumps(a)), copy.deepcopy(a), copy.copy(a)):
        assert clone == a and hash(clone) == hash(a)
        with pytest.raises(TypeError):
            clone.lanes["x/y"] = "latest"


def test_as_config_accepts_a_config_a_url_or_nothing(monkeypatch):
    monkeypatch.setenv("STG_NAMESPACE", "rig9")
    config = BusConfig(url="ipc:///tmp/stg-test/bus")
    assert as_config(config) is config
    assert as_config("tcp://127.0.0.1:7400") == BusConfig(url="tcp://127.0.0.1:7400", namespace="rig9")
    monkeypatch.setenv("STG_BUS", "ipc:///tmp/stg-test/env")
    assert as_config(None).url == "ipc:///tmp/stg-test/env"
