"""Nodes: the processes of the running system, and the runtime they share.

Each node is its own OS process, started by ``stg-launch`` or by hand:

    python -m stg_node.nodes ingest --param source=dataset --param path=runs/demo/subject

| kind | module | what it does |
|---|---|---|
| ingest | :mod:`.ingest` | replays a dataset, a video file, a V4L2 camera or an OAK camera on camera/frame |
| tracker | :mod:`.tracker` | body/pose per frame: a dataset's SMPL fits, or live (:mod:`.live_tracking`) |
| trainer | :mod:`.trainer` | trains the avatar online; avatar/snapshot, trainer/metrics, checkpoints |
| renderer | :mod:`.renderer` | renders avatar/view requests or default views on avatar/image |
| recorder | :mod:`.recorder` | records the bus into an MCAP file (stg-bag record as a node) |
| foxglove | :mod:`.foxglove_bridge` | serves the bus live to Foxglove (Foxglove WebSocket, foxglove-sdk) |
| web | :mod:`.web` | serves a page: the live avatar for a robot's screen, an operator view |

:mod:`.runtime` is the node base class and event loop, :mod:`.params` the typed parameters.
Node modules import heavy packages (torch, OpenCV, depthai) only when a node starts, so that
listing kinds or validating a launch file stays fast.
"""

from __future__ import annotations

import importlib

#: kind -> "module:Class". A launch file may also name any "package.module:Class" directly.
NODE_KINDS = {
    "ingest": "stg_node.nodes.ingest:IngestNode",
    "tracker": "stg_node.nodes.tracker:TrackerNode",
    "trainer": "stg_node.nodes.trainer:TrainerNode",
    "renderer": "stg_node.nodes.renderer:RendererNode",
    "recorder": "stg_node.nodes.recorder:RecorderNode",
    "foxglove": "stg_node.nodes.foxglove_bridge:FoxgloveNode",
    "web": "stg_node.nodes.web:WebNode",
}


class UnknownNodeKind(ValueError):
    """A node kind names no known node and no importable ``module:Class``."""


def load_node_class(kind: str) -> type:
    """The Node subclass for ``kind`` (a registered name or ``module:Class``)."""
    from stg_node.nodes.runtime import Node

    target = NODE_KINDS.get(kind, kind)
    module_name, sep, class_name = target.partition(":")
    if not sep or not module_name or not class_name:
        raise UnknownNodeKind(
            f"unknown node kind {kind!r}; known kinds: {', '.join(NODE_KINDS)} (or module:Class)"
        )
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise UnknownNodeKind(f"node kind {kind!r}: cannot import {module_name!r} ({exc})") from exc
    cls = getattr(module, class_name, None)
    if not (isinstance(cls, type) and issubclass(cls, Node)):
        raise UnknownNodeKind(f"node kind {kind!r}: {target!r} is not a stg_node.nodes.runtime.Node subclass")
    return cls


__all__ = ["NODE_KINDS", "UnknownNodeKind", "load_node_class"]
