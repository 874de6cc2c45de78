"""The schema record a recording carries for each message type: the type's proto/ YAML.

In a checkout (and an editable install) that is the hand-written file in proto/, comments
and all. Where proto/ is not beside the package (a wheel), the same schema is rendered from
the message class (stg_node.bus.schema.schema_of), which tests/bus/test_bus_proto.py holds
equal to the file field by field.
"""

from __future__ import annotations

import functools
from pathlib import Path

import yaml

from stg_node.bus import REGISTRY
from stg_node.bus.schema import schema_of

PROTO_DIR = Path(__file__).resolve().parents[3] / "proto"


@functools.cache
def schema_data(type_name: str) -> bytes | None:
    """The YAML schema of message type ``type_name``; None for a type this package does not know."""
    cls = REGISTRY.get(type_name)
    if cls is None:
        return None
    path = PROTO_DIR / f"{type_name.lower()}.yaml"
    if path.is_file():
        return path.read_bytes()
    return yaml.safe_dump(schema_of(cls), sort_keys=False, width=110).encode()
