"""Run one node as its own process: ``python -m stg_node.nodes KIND [options]`` (or ``stg-node``).

    python -m stg_node.nodes ingest --name cam0 --param source=video --param path=clip.mp4
    python -m stg_node.nodes renderer --params '{"size": 256}' --bus tcp://127.0.0.1:7400
    python -m stg_node.nodes trainer --describe          # its parameters, types, defaults
    python -m stg_node.nodes --list                      # the node kinds
    stg-node foxglove --port 8765                        # the bus, live in Foxglove
    stg-node web --port 8080 [--host 0.0.0.0]            # the page: / (operator), /avatar (screen)

``--params`` takes JSON (or ``@file.json``); ``--param k=v`` (repeatable) wins over it, its value
parsed as the parameter's type. ``--remap from:=to`` renames a topic for this node; ``--ack TOPIC``
acknowledges each message taken from TOPIC on node/ack (lockstep playback). Exit codes:
0 stopped cleanly (also on SIGINT/SIGTERM), 1 the node failed, 2 bad usage or bad parameters.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path

from stg_node.bus.config import BusConfig
from stg_node.cli.bus_options import add_bus_options, bus_config
from stg_node.cli.runner import UsageError, add_log_level_option, run_main
from stg_node.nodes import NODE_KINDS, UnknownNodeKind, load_node_class
from stg_node.nodes.params import ParamError, describe_params, parse_params
from stg_node.nodes.runtime import ENV_RESPAWN, ENV_STANDBY, name_process
from stg_node.signals import StopSignals

log = logging.getLogger("stg_node.nodes")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m stg_node.nodes",
        description="Run one stg_node node as a process.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__,
    )
    parser.add_argument("kind", nargs="?", help=f"node kind ({', '.join(NODE_KINDS)}) or module:Class")
    parser.add_argument("--name", help="node name: its src on the bus and in logs (default: the kind)")
    parser.add_argument("--params", default="{}", metavar="JSON", help="parameters as JSON, or @FILE")
    parser.add_argument("--param", action="append", default=[], metavar="K=V", help="one parameter")
    parser.add_argument("--remap", action="append", default=[], metavar="FROM:=TO", help="rename a topic")
    parser.add_argument(
        "--lane", action="append", default=[], metavar="TOPIC=LANE", help="move a topic to another lane"
    )
    parser.add_argument("--port", type=int, metavar="N", help="foxglove, web: same as --param port=N")
    parser.add_argument("--host", metavar="ADDR", help="foxglove, web: same as --param host=ADDR")
    parser.add_argument("--heartbeat", type=float, default=1.0, metavar="S", help="NodeStatus period")
    parser.add_argument(
        "--ack",
        action="append",
        default=[],
        metavar="TOPIC",
        help="lockstep: publish an Ack on node/ack for each message of TOPIC (as subscribed; '*': all) "
        "once handled (repeatable)",
    )
    add_log_level_option(parser)
    parser.add_argument("--list", action="store_true", help="list the node kinds and exit")
    parser.add_argument("--describe", action="store_true", help="print the kind's parameters and exit")
    add_bus_options(parser)
    return parser


def _pairs(items: list[str], sep: str, what: str) -> dict[str, str]:
    out = {}
    for item in items:
        key, found, value = item.partition(sep)
        if not found or not key.strip():
            raise ValueError(f"{what} {item!r} must look like NAME{sep}VALUE")
        out[key.strip()] = value
    return out


def _load_params(text: str) -> dict:
    if text.startswith("@"):
        text = Path(text[1:]).read_text()
    try:
        values = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"--params is not valid JSON: {exc}") from exc
    if not isinstance(values, dict):
        raise ValueError(f"--params must be a JSON object, got {type(values).__name__}")
    return values


def describe(kind: str, cls: type) -> str:
    lines = [f"{kind}: {(cls.__doc__ or '').strip().splitlines()[0] if cls.__doc__ else ''}", ""]
    for info in describe_params(cls.Params):
        default = "(required)" if info.required else f"= {info.default!r}"
        unit = f" [{info.unit}]" if info.unit else ""
        lines.append(f"  {info.name}: {info.type} {default}{unit}")
        if info.doc:
            lines.append(f"      {info.doc}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    if args.list:
        for kind, target in NODE_KINDS.items():
            print(f"{kind:10s} {target}")
        return 0
    if not args.kind:
        raise UsageError("a node kind is required (--list shows them)")
    name = args.name or args.kind.rpartition(":")[2].lower()
    try:
        cls = load_node_class(args.kind)
        if args.describe:
            print(describe(args.kind, cls))
            return 0
        values = {**_load_params(args.params), **_pairs(args.param, "=", "--param")}
        for option in ("port", "host"):
            if getattr(args, option) is not None:
                if option not in {info.name for info in describe_params(cls.Params)}:
                    raise ValueError(f"--{option}: node kind {args.kind!r} has no parameter {option!r}")
                values[option] = getattr(args, option)
        params = parse_params(cls.Params, values, where=f"node {name!r} ({args.kind})")
        remap = _pairs(args.remap, ":=", "--remap")
        config: BusConfig = bus_config(args)
        if args.lane:
            config = config.with_(lanes=_pairs(args.lane, "=", "--lane"))
    except (UnknownNodeKind, ParamError, ValueError, OSError) as exc:
        raise UsageError(str(exc)) from exc
    name_process(name)
    if os.environ.get(ENV_STANDBY):
        taking_over = stand_by(name, cls, params)
        if not taking_over:
            return 0
    with StopSignals() as stop:  # the first SIGINT/SIGTERM ends the loop, teardown still runs
        try:
            node = cls(name, params, config, remap=remap, heartbeat_s=args.heartbeat, stop=stop, ack=args.ack)
        except KeyboardInterrupt:
            return 0
        except (OSError, ValueError) as exc:  # e.g. the bus URL cannot be reached
            log.error("%s: cannot start: %s", name, exc)
            return 1
        return node.execute()


def stand_by(name: str, cls: type, params) -> bool:
    """A standby copy (stg-launch ``standby: true``): prepare the node (imports done), then wait
    for the launcher on stdin. ``go N``: take over as the node's respawn N (True); end of file:
    not needed after all (False). Ctrl-C / SIGTERM while waiting end it like any node (exit 0)."""
    try:
        cls.prepare(params)
    except Exception as exc:  # warming up is best effort: the real setup reports real problems
        log.warning("%s: standby preparation failed: %s", name, exc)
    log.info("standing by (pid %d)", os.getpid())
    for line in sys.stdin:
        word, _, respawns = line.strip().partition(" ")
        if word == "go":
            os.environ.pop(ENV_STANDBY, None)
            os.environ[ENV_RESPAWN] = respawns if respawns.isdigit() else "1"
            log.info("taking over (respawn %s)", os.environ[ENV_RESPAWN])
            return True
    return False


def main(argv=None) -> int:
    return run_main(build_parser(), run, argv, stop_is_success=True)


if __name__ == "__main__":
    sys.exit(main())
