"""Launch files -> a checked LaunchSpec: arguments, substitutions, includes, nodes, their parameters.

The format (docs/LAUNCH.md, schema in launch.schema.json beside this module):

    description: what this launch does
    args:                                   # overridable on the command line: name:=value
      bus: {default: "", doc: bus URL (empty = the default ipc bus)}
      out: runs/demo                        # a bare value is the default
    env: {STG_THREADS: "1"}                 # for every process of this file
    bus: {url: $(arg bus), namespace: "", lanes: {camera/frame: reliable}, broker: true}
    include:
      - {file: sensors.yaml, args: {camera: "0"}, namespace: rig1}
    nodes:
      - name: ingest
        kind: ingest                        # a node kind (python -m stg_node.nodes), or module: / cmd:
        params: {source: dataset, path: $(arg out)/subject}
        respawn: true
        after: [synth]

Everything the format allows is declared once, as the dataclasses below (typed with
stg_node.nodes.params, which also coerces the strings that substitutions produce); the JSON
schema is generated from them (:mod:`.schema`). Every error is a :class:`LaunchFileError`
naming the file and line.
"""

from __future__ import annotations

import dataclasses
import json
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from stg_node.bus.config import BusConfig, default_url
from stg_node.bus.topics import LANES
from stg_node.launch.substitute import Scope, SubstitutionError, substitute
from stg_node.launch.yamlfile import LaunchFileError, Located, load_file
from stg_node.nodes import UnknownNodeKind, load_node_class
from stg_node.nodes.params import ParamError, param, parse_params

NAME_PATTERN = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*$")
NAMESPACE_PATTERN = re.compile(r"^([A-Za-z0-9_][A-Za-z0-9_.\-]*(/[A-Za-z0-9_][A-Za-z0-9_.\-]*)*)?$")
READY_FORMS = ("heartbeat", "started", "exit", "file:PATH", "delay:SECONDS")
MAX_INCLUDE_DEPTH = 16

# --- what a launch file may say (one source of truth for the parser and the JSON schema) -----------


@dataclass
class NodeEntry:
    """One process in a launch file."""

    name: str = param(doc="unique name: the node's src on the bus and its output prefix")
    kind: str | None = param(None, doc="node kind (ingest, tracker, trainer, renderer) or module:Class")
    module: str | None = param(None, doc="a Python module to run as `python -m MODULE ARGS`")
    cmd: list[str] | None = param(None, doc="a program and its arguments")
    params: dict[str, Any] = param({}, doc="node parameters (kind nodes), checked against the kind")
    args: list[str] = param([], doc="extra command-line arguments (module and cmd nodes)")
    env: dict[str, str] = param({}, doc="environment variables for this process")
    namespace: str = param("", doc="bus namespace of this node (joined to an include's namespace)")
    remap: dict[str, str] = param({}, doc="topic renames for this node: {from: to}")
    respawn: bool = param(False, doc="restart the process when it fails (exit code != 0)")
    respawn_delay: float = param(1.0, min=0.0, unit="s", doc="first restart delay; doubles per failure")
    respawn_max_delay: float = param(30.0, min=0.0, unit="s", doc="longest restart delay")
    max_respawns: int = param(-1, min=-1, doc="restarts allowed (-1: no limit)")
    standby: bool = param(
        False,
        doc="kind nodes with respawn: keep a second copy started and prepared (imports done), waiting; "
        "a respawn hands over to it at once (costs that copy's memory)",
    )
    required: bool = param(False, doc="when this node ends (after any respawns), the launch ends")
    after: list[str] = param([], doc="start only when these nodes are ready")
    ready: str = param(
        "",
        doc="when the node counts as ready: heartbeat (kind nodes' default), started (others'), "
        "exit (exited 0), file:PATH, delay:SECONDS",
    )
    ready_timeout: float = param(
        120.0, min=0.0, unit="s", doc="fail the launch if not ready by then (0: wait)"
    )
    sigint_timeout: float = param(5.0, min=0.0, unit="s", doc="on shutdown: wait after SIGINT before SIGTERM")
    sigterm_timeout: float = param(5.0, min=0.0, unit="s", doc="then wait after SIGTERM before SIGKILL")
    heartbeat: float = param(1.0, min=0.05, unit="s", doc="NodeStatus period (kind nodes)")
    ack: list[str] = param(
        [],
        doc="kind nodes, lockstep: publish an Ack on node/ack for each message taken from these "
        "topics (as the node subscribes them; '*': all) once handled, for stg-bag play --lockstep",
    )
    nice: int = param(
        0,
        min=0,
        max=19,
        doc="CPU niceness added to the process and every thread it starts (0: as the launcher; "
        "19: the smallest share of a busy CPU): background work, e.g. a trainer beside a live renderer",
    )
    cwd: str | None = param(None, doc="working folder (default: where stg-launch runs)")
    if_: bool = param(True, doc="(written `if:`) start the node only if true")
    unless: bool = param(False, doc="skip the node if true")


@dataclass
class IncludeEntry:
    """Another launch file, read in place."""

    file: str = param(doc="path, relative to the including file")
    args: dict[str, str] = param(
        {}, doc="its arguments (others: the includer's of the same name, else defaults)"
    )
    namespace: str = param("", doc="namespace for all of its nodes")
    if_: bool = param(True, doc="(written `if:`) include only if true")
    unless: bool = param(False, doc="skip the include if true")


@dataclass
class BusEntry:
    """Where the nodes meet (top-level file only)."""

    url: str = param("", doc="bus URL; empty = $STG_BUS or the default ipc path")
    namespace: str = param("", doc="namespace for every node")
    lanes: dict[str, str] = param({}, doc="lane overrides: {topic: latest|reliable|bulk}")
    broker: bool = param(True, doc="start a broker (false: one already runs)")
    broker_urls: list[str] = param([], doc="more URLs for the broker to serve (e.g. tcp for a robot)")
    keys: str | None = param(None, doc="CURVE key folder for tcp (stg-keys)")


@dataclass
class LaunchEntry:
    """The top level of a launch file."""

    description: str = param("", doc="what this launch does")
    args: dict[str, Any] = param({}, doc="arguments: NAME: DEFAULT or NAME: {default: D, doc: TEXT}")
    env: dict[str, str] = param({}, doc="environment variables for every process of this file")
    bus: dict[str, Any] = param({}, doc="the bus (top-level file only)")
    include: list[dict[str, Any]] = param([], doc="other launch files")
    nodes: list[dict[str, Any]] = param([], doc="the processes")


# --- what the launcher gets -------------------------------------------------------------------------


@dataclass(frozen=True)
class ArgInfo:
    name: str
    default: str | None  # None: required
    doc: str


@dataclass
class NodeSpec:
    """One process to supervise, fully resolved."""

    entry: NodeEntry
    name: str  # with the include namespace, e.g. rig1/ingest
    namespace: str  # bus namespace (launch, include and node namespaces joined)
    env: dict[str, str]
    params: Any  # the kind's typed params dataclass, or None for module/cmd nodes
    source: str  # "file:line" of the entry
    ready: str  # "heartbeat", "started", "exit", "file:PATH" or "delay:S"
    after: list[str]  # full names (relative names joined to the file's namespace; "/x" is absolute)

    def __getattr__(self, name):  # entry fields read as the spec's own (respawn, after, ...)
        if name == "entry":
            raise AttributeError(name)
        return getattr(self.entry, name)

    def command(self, bus: BusSection) -> list[str]:
        e = self.entry
        if e.kind is not None:
            cmd = [sys.executable, "-m", "stg_node.nodes", e.kind, "--name", self.name]
            cmd += ["--params", json.dumps(dataclasses.asdict(self.params)), "--bus", bus.url]
            cmd += ["--heartbeat", str(e.heartbeat)]
            for topic in e.ack:
                cmd += ["--ack", topic]
            if self.namespace:
                cmd += ["--namespace", self.namespace]
            if bus.keys:
                cmd += ["--keys", bus.keys]
            for src, dst in e.remap.items():
                cmd += ["--remap", f"{src}:={dst}"]
            for topic, lane in bus.lanes.items():
                cmd += ["--lane", f"{topic}={lane}"]
            return cmd
        if e.module is not None:
            return [sys.executable, "-m", e.module, *e.args]
        return [*e.cmd, *e.args]


@dataclass
class BusSection:
    url: str
    namespace: str
    lanes: dict[str, str]
    broker: bool
    broker_urls: list[str]
    keys: str | None

    def config(self, namespace: str | None = None) -> BusConfig:
        return BusConfig(
            url=self.url,
            namespace=self.namespace if namespace is None else namespace,
            keys=self.keys,
            lanes=dict(self.lanes),
        )


@dataclass
class LaunchSpec:
    path: Path
    description: str
    args: list[ArgInfo]
    arg_values: dict[str, str]
    bus: BusSection
    nodes: list[NodeSpec] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)  # names left out by if/unless

    def node(self, name: str) -> NodeSpec:
        for spec in self.nodes:
            if spec.name == name:
                return spec
        raise KeyError(name)


# --- parsing ------------------------------------------------------------------------------------------


def parse_overrides(items: list[str]) -> dict[str, str]:
    """``name:=value`` command-line arguments -> dict; ValueError for anything else."""
    out = {}
    for item in items:
        name, sep, value = item.partition(":=")
        if not sep or not NAME_PATTERN.match(name):
            raise ValueError(f"launch argument {item!r} must look like name:=value")
        out[name] = value
    return out


def _join_ns(*parts: str) -> str:
    return "/".join(p.strip("/") for p in parts if p and p.strip("/"))


def _rename_if(raw: dict) -> dict:
    if "if_" in raw:
        raise ValueError("write 'if:', not 'if_:'")
    return {("if_" if k == "if" else k): v for k, v in raw.items()}


def _typed(cls, raw, doc: Located, key: tuple, what: str):
    """Parse one mapping of the file as ``cls``; errors located at the offending key."""
    if not isinstance(raw, dict):
        raise doc.error(key, f"{what} must be a mapping, got {type(raw).__name__}")
    try:
        raw = _rename_if(raw)
    except ValueError as exc:
        raise doc.error(key, str(exc)) from None
    try:
        return parse_params(cls, raw, where=what)
    except ParamError as exc:
        name = exc.name.split("[")[0].split(".")[0] if exc.name else None
        name = "if" if name == "if_" else name
        problem = exc.problem if exc.name is None else f"{exc.name}: {exc.problem}"
        problem = problem.replace("if_", "if")
        raise doc.error((*key, name) if name else key, f"{what}: {problem}") from None


def _substituted(value, doc: Located, key: tuple, scope: Scope):
    """Substitute every string under ``value``; errors located at the string's line."""
    if isinstance(value, str):
        try:
            return substitute(value, scope)
        except SubstitutionError as exc:
            raise doc.error(key, str(exc)) from None
    if isinstance(value, dict):
        return {k: _substituted(v, doc, (*key, k), scope) for k, v in value.items()}
    if isinstance(value, list):
        return [_substituted(v, doc, (*key, i), scope) for i, v in enumerate(value)]
    return value


def _declared_args(raw, doc: Located) -> list[ArgInfo]:
    if not isinstance(raw, dict):
        raise doc.error(("args",), "args must be a mapping of NAME: DEFAULT or NAME: {default, doc}")
    out = []
    for name, value in raw.items():
        if not isinstance(name, str) or not NAME_PATTERN.match(name):
            raise doc.error(("args", name), f"argument name {name!r} must be a word (letters, digits, _ . -)")
        if isinstance(value, dict):
            unknown = set(value) - {"default", "doc"}
            if unknown:
                raise doc.error(
                    ("args", name), f"argument {name!r}: unknown keys {sorted(unknown)} (default, doc)"
                )
            default = value.get("default")
            text = value.get("doc", "")
            out.append(ArgInfo(name, None if default is None else _scalar_text(default), str(text)))
        elif isinstance(value, (list,)):
            raise doc.error(("args", name), f"argument {name!r}: a default must be a scalar")
        else:
            out.append(ArgInfo(name, None if value is None else _scalar_text(value), ""))
    return out


def _scalar_text(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


class _Reader:
    """Reads a launch file and its includes into one LaunchSpec."""

    def __init__(self):
        self.nodes: list[NodeSpec] = []
        self.skipped: list[str] = []
        self.seen_names: dict[str, str] = {}

    def read(
        self,
        path: Path,
        given: dict[str, str],
        inherited: dict[str, str],
        namespace: str,
        stack: tuple[Path, ...],
        include_key: tuple[Located, tuple] | None,
    ) -> tuple[Located, LaunchEntry, list[ArgInfo], dict[str, str]]:
        doc = load_file(path)
        if doc.data is None:
            doc.data = {}
        entry = _typed(LaunchEntry, doc.data, doc, (), "launch file")
        declared = _declared_args(entry.args, doc)
        names = {a.name for a in declared}
        for name in given:
            if name not in names:
                known = ", ".join(sorted(names)) or "none"
                if include_key is None:
                    raise LaunchFileError(path, None, f"unknown launch argument {name!r} (declared: {known})")
                parent, key = include_key
                raise parent.error(
                    (*key, "args", name), f"{path.name} has no argument {name!r} (declared: {known})"
                )
        values = {}
        for arg in declared:
            if arg.name in given:
                values[arg.name] = given[arg.name]
            elif arg.name in inherited:
                values[arg.name] = inherited[arg.name]
            elif arg.default is not None:
                values[arg.name] = arg.default
            else:
                hint = f" ({arg.doc})" if arg.doc else ""
                raise doc.error(
                    ("args", arg.name),
                    f"launch argument {arg.name!r} is required: pass {arg.name}:=VALUE{hint}",
                )
        scope = Scope(values, path.parent.resolve())
        file_env = {str(k): _scalar_text(v) for k, v in _substituted(entry.env, doc, ("env",), scope).items()}

        for i, raw in enumerate(entry.include):
            key = ("include", i)
            inc = _typed(IncludeEntry, _substituted(raw, doc, key, scope), doc, key, f"include #{i + 1}")
            if not inc.if_ or inc.unless:
                continue
            target = Path(inc.file).expanduser()
            if not target.is_absolute():
                target = path.parent / target
            target = target.resolve()
            if target in stack:
                chain = " -> ".join(p.name for p in (*stack, target))
                raise doc.error((*key, "file"), f"include cycle: {chain}")
            if len(stack) >= MAX_INCLUDE_DEPTH:
                raise doc.error((*key, "file"), f"includes nested deeper than {MAX_INCLUDE_DEPTH}")
            if not target.is_file():
                raise doc.error((*key, "file"), f"included file {target} does not exist")
            if not NAMESPACE_PATTERN.match(inc.namespace):
                raise doc.error(
                    (*key, "namespace"), f"namespace {inc.namespace!r} is not a valid topic prefix"
                )
            self.read(
                target,
                {k: _scalar_text(v) for k, v in inc.args.items()},
                values,
                _join_ns(namespace, inc.namespace),
                (*stack, target),
                (doc, key),
            )

        for i, raw in enumerate(entry.nodes):
            self._node(doc, ("nodes", i), raw, scope, namespace, file_env)
        return doc, entry, declared, values

    def _node(self, doc: Located, key: tuple, raw, scope: Scope, namespace: str, file_env: dict) -> None:
        label = f"node #{key[1] + 1}"
        if isinstance(raw, dict) and isinstance(raw.get("name"), str):
            label = f"node {raw['name']!r}"
        entry: NodeEntry = _typed(NodeEntry, _substituted(raw, doc, key, scope), doc, key, label)
        if not NAME_PATTERN.match(entry.name):
            raise doc.error((*key, "name"), f"{label}: name must be a word (letters, digits, _ . -)")
        name = _join_ns(namespace, entry.name)
        if not entry.if_ or entry.unless:
            self.skipped.append(name)
            return
        where = f"{doc.path}:{doc.line(key)}"
        if name in self.seen_names:
            raise doc.error(
                (*key, "name"), f"{label}: a node named {name!r} already exists ({self.seen_names[name]})"
            )
        self.seen_names[name] = where
        how = [k for k in ("kind", "module", "cmd") if getattr(entry, k) is not None]
        if len(how) != 1:
            raise doc.error(key, f"{label}: give exactly one of kind, module or cmd (got {how or 'none'})")
        if entry.cmd is not None and not entry.cmd:
            raise doc.error((*key, "cmd"), f"{label}: cmd is empty")
        if entry.kind is None and entry.params:
            raise doc.error(
                (*key, "params"), f"{label}: params are for kind nodes; pass args to module/cmd nodes"
            )
        if entry.kind is None and entry.ack:
            raise doc.error((*key, "ack"), f"{label}: ack is for kind nodes (their runtime sends the Acks)")
        if entry.standby and (entry.kind is None or not entry.respawn):
            raise doc.error(
                (*key, "standby"),
                f"{label}: standby is for kind nodes with respawn: true (it takes over on a respawn)",
            )
        if not NAMESPACE_PATTERN.match(entry.namespace):
            raise doc.error(
                (*key, "namespace"), f"{label}: namespace {entry.namespace!r} is not a valid topic prefix"
            )
        ready = entry.ready or ("heartbeat" if entry.kind is not None else "started")
        self._check_ready(ready, entry, doc, key, label)
        typed = None
        if entry.kind is not None:
            try:
                cls = load_node_class(entry.kind)
            except UnknownNodeKind as exc:
                raise doc.error((*key, "kind"), f"{label}: {exc}") from None
            try:
                typed = parse_params(cls.Params, entry.params, where=label)
            except ParamError as exc:
                at = (*key, "params", exc.name.split("[")[0].split(".")[0]) if exc.name else (*key, "params")
                raise doc.error(at, str(exc)) from None
        env = {**file_env, **{str(k): _scalar_text(v) for k, v in entry.env.items()}}
        self.nodes.append(
            NodeSpec(
                entry=entry,
                name=name,
                namespace=_join_ns(namespace, entry.namespace),
                env=env,
                params=typed,
                source=where,
                ready=ready,
                after=[d[1:] if d.startswith("/") else _join_ns(namespace, d) for d in entry.after],
            )
        )

    @staticmethod
    def _check_ready(ready: str, entry: NodeEntry, doc: Located, key: tuple, label: str) -> None:
        kind, _, value = ready.partition(":")
        ok = ready in ("heartbeat", "started", "exit") or (kind == "file" and value)
        if kind == "delay":
            try:
                ok = float(value) >= 0
            except ValueError:
                ok = False
        if not ok:
            raise doc.error(
                (*key, "ready"), f"{label}: ready {ready!r} is not one of {', '.join(READY_FORMS)}"
            )
        if ready == "heartbeat" and entry.kind is None:
            raise doc.error(
                (*key, "ready"),
                f"{label}: only kind nodes send heartbeats; use started, exit, file: or delay:",
            )
        if ready == "exit" and entry.respawn:
            raise doc.error((*key, "ready"), f"{label}: a node that is ready when it exits cannot respawn")


def read_launch(path: str | Path, overrides: dict[str, str] | None = None) -> LaunchSpec:
    """Read and check a launch file (and its includes) with ``overrides`` (``name:=value``) applied."""
    path = Path(path).resolve()
    reader = _Reader()
    doc, entry, declared, values = reader.read(path, dict(overrides or {}), {}, "", (path,), None)
    scope = Scope(values, path.parent)
    bus_raw = _substituted(entry.bus, doc, ("bus",), scope)
    bus = _typed(BusEntry, bus_raw, doc, ("bus",), "bus")
    for topic, lane in bus.lanes.items():
        if lane not in LANES:
            raise doc.error(
                ("bus", "lanes", topic), f"lane {lane!r} for {topic!r} is not one of {sorted(LANES)}"
            )
    if not NAMESPACE_PATTERN.match(bus.namespace):
        raise doc.error(("bus", "namespace"), f"namespace {bus.namespace!r} is not a valid topic prefix")
    section = BusSection(
        url=bus.url or BusConfig.from_env().url or default_url(),
        namespace=bus.namespace,
        lanes=dict(bus.lanes),
        broker=bus.broker,
        broker_urls=list(bus.broker_urls),
        keys=bus.keys,
    )
    try:
        section.config()
        for url in section.broker_urls:
            BusConfig(url=url)
    except ValueError as exc:
        raise doc.error(("bus",), f"bus: {exc}") from None
    for spec in reader.nodes:
        spec.namespace = _join_ns(section.namespace, spec.namespace)
    if not reader.nodes and not reader.skipped:  # an empty or cut-off file: say so, do not run nothing
        raise doc.error(("nodes",), "nothing to launch: the file (and its includes) lists no nodes")
    _check_graph(reader.nodes, set(reader.skipped))
    return LaunchSpec(
        path=path,
        description=entry.description,
        args=declared,
        arg_values=values,
        bus=section,
        nodes=reader.nodes,
        skipped=reader.skipped,
    )


def _check_graph(nodes: list[NodeSpec], skipped: set[str]) -> None:
    names = {n.name for n in nodes}
    for spec in nodes:
        for dep in spec.after:
            if dep not in names and dep not in skipped:
                file, _, line = spec.source.rpartition(":")
                raise LaunchFileError(file, int(line), f"node {spec.name!r}: after names no node {dep!r}")
    # cycles: depth-first search over 'after'
    deps = {n.name: [d for d in n.after if d in names] for n in nodes}
    state: dict[str, int] = {}

    def visit(name: str, chain: list[str]) -> None:
        if state.get(name) == 2:
            return
        if state.get(name) == 1:
            cycle = " -> ".join([*chain[chain.index(name) :], name])
            spec = next(n for n in nodes if n.name == name)
            file, _, line = spec.source.rpartition(":")
            raise LaunchFileError(file, int(line), f"start order has a cycle: {cycle}")
        state[name] = 1
        for dep in deps[name]:
            visit(dep, [*chain, name])
        state[name] = 2

    for n in nodes:
        visit(n.name, [])
