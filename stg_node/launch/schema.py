"""The launch-file JSON schema, generated from the dataclasses that the parser itself uses.

``stg-launch --schema`` prints it; docs/launch.schema.json is its committed copy (a test keeps the
two equal), for editors (YAML language servers) and other tools. Values may always be ``$(...)``
substitutions, which only the launcher can resolve; ``stg-launch --validate`` checks everything,
including each node's parameters against its kind.
"""

from __future__ import annotations

import json

from stg_node.launch.spec import BusEntry, IncludeEntry, LaunchEntry, NodeEntry
from stg_node.nodes import NODE_KINDS, load_node_class
from stg_node.nodes.params import params_json_schema

SCHEMA_ID = "https://stg-node.invalid/launch.schema.json"


def _rename_if(schema: dict) -> dict:
    props = schema["properties"]
    if "if_" in props:
        props["if"] = props.pop("if_")
    return schema


def launch_schema() -> dict:
    node = _rename_if(params_json_schema(NodeEntry))
    node["oneOf"] = [{"required": [k]} for k in ("kind", "module", "cmd")]
    node["allOf"] = [
        {
            "if": {"properties": {"kind": {"const": kind}}, "required": ["kind"]},
            "then": {"properties": {"params": params_json_schema(load_node_class(kind).Params)}},
        }
        for kind in NODE_KINDS
    ]
    include = _rename_if(params_json_schema(IncludeEntry))
    top = params_json_schema(LaunchEntry)
    props = top["properties"]
    props["args"] = {
        "description": props["args"]["description"],
        "type": "object",
        "propertyNames": {"pattern": r"^[A-Za-z_][A-Za-z0-9_.\-]*$"},
        "additionalProperties": {
            "anyOf": [
                {"type": ["string", "number", "boolean", "null"]},
                {
                    "type": "object",
                    "properties": {
                        "default": {"type": ["string", "number", "boolean", "null"]},
                        "doc": {"type": "string"},
                    },
                    "additionalProperties": False,
                },
            ]
        },
    }
    props["bus"] = {"description": props["bus"]["description"], **params_json_schema(BusEntry)}
    props["include"] = {"description": props["include"]["description"], "type": "array", "items": include}
    props["nodes"] = {"description": props["nodes"]["description"], "type": "array", "items": node}
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": SCHEMA_ID,
        "title": "stg-launch launch file",
        "description": "YAML launch file for stg-launch (docs/LAUNCH.md)",
        **top,
    }


def schema_text() -> str:
    return json.dumps(launch_schema(), indent=2, sort_keys=False) + "\n"
