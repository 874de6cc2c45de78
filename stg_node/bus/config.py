"""Where the bus is and how to reach it: BusConfig, lane endpoints, namespaces, environment.

One base URL names a whole bus; each lane (topics.LANES) has two endpoints derived from
it, an ``in`` side that publishers connect to and an ``out`` side that subscribers
connect to. The broker binds both; without a broker a publisher binds the ``out`` side
itself (``bind=True``) and subscribers do not notice the difference.

    ipc:///run/user/1000/stg/bus  ->  ipc:///run/user/1000/stg/bus.latest.in, ...bus.latest.out,
                                      ...bus.reliable.in, ...bus.reliable.out, ...bus.bulk.in/.out
    tcp://host:7400               ->  latest 7400 (in) / 7401 (out), reliable 7402 / 7403,
                                      bulk 7404 / 7405
    inproc://name                 ->  inproc://name.latest.in, ... (one process, one context)

Environment (read by :meth:`BusConfig.from_env`): STG_BUS (the URL), STG_NAMESPACE,
STG_BUS_KEYS (CURVE key directory), STG_BUS_KEY_NAME (this client's key name).
"""

from __future__ import annotations

import os
import socket
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import MappingProxyType

from stg_node.bus.codec import expected_type
from stg_node.bus.messages import TOPIC_TYPES
from stg_node.bus.topics import DEFAULT_LANE, LANES, Lane, base_name, check_namespace, join_namespace

ENV_BUS = "STG_BUS"
ENV_NAMESPACE = "STG_NAMESPACE"
ENV_KEYS = "STG_BUS_KEYS"
ENV_KEY_NAME = "STG_BUS_KEY_NAME"
DEFAULT_TCP_PORT = 7400
SIDES = ("in", "out")
# sockaddr_un.sun_path is 108 bytes on Linux, including the terminating NUL.
_MAX_IPC_PATH = 107


def default_url() -> str:
    """ipc in the user's runtime dir ($XDG_RUNTIME_DIR/stg/bus, else /tmp/stg-UID/bus)."""
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    base = Path(runtime) / "stg" if runtime else Path(tempfile.gettempdir()) / f"stg-{os.getuid()}"
    return f"ipc://{base}/bus"


def parse_url(url: str) -> tuple[str, str, int | None]:
    """Split a bus URL into (transport, address, port); a clear ValueError when it is not one."""
    scheme, sep, rest = url.partition("://")
    if not sep or not rest:
        raise ValueError(f"bus URL {url!r} must look like ipc:///path, tcp://host:port or inproc://name")
    if scheme in ("ipc", "inproc"):
        return scheme, rest, None
    if scheme == "tcp":
        host, colon, port_text = rest.rpartition(":")
        if not colon or not host or not port_text.isdigit():
            raise ValueError(
                f"bus URL {url!r} needs a host and a port, e.g. tcp://127.0.0.1:{DEFAULT_TCP_PORT}"
            )
        port = int(port_text)
        last = port + 2 * len(LANES) - 1
        if not 1 <= port or last > 65535:
            raise ValueError(f"bus URL {url!r}: ports {port}..{last} must lie within 1..65535")
        return scheme, host, port
    raise ValueError(
        f"bus URL {url!r}: transport {scheme!r} is not ipc, tcp or inproc "
        "(ipc:///path, tcp://host:port or inproc://name)"
    )


def lane_endpoint(url: str, lane: str | Lane, side: str) -> str:
    """The ZeroMQ endpoint of one side ('in' or 'out') of one lane of the bus at ``url``."""
    lane = LANES[lane] if isinstance(lane, str) else lane
    if side not in SIDES:
        raise ValueError(f"side must be one of {SIDES}, got {side!r}")
    transport, address, port = parse_url(url)
    if transport == "tcp":
        return f"tcp://{address}:{port + 2 * lane.index + SIDES.index(side)}"
    endpoint = f"{transport}://{address}.{lane.name}.{side}"
    if transport == "ipc" and len(address) + len(".reliable.out") > _MAX_IPC_PATH:
        raise ValueError(
            f"ipc path {address!r} is too long for a Unix socket (max ~{_MAX_IPC_PATH - 13} chars)"
        )
    return endpoint


@dataclass(frozen=True)
class BusConfig:
    """How one node reaches the bus. Frozen (``lanes`` too, a read-only mapping): share one
    freely between threads and objects; make variants with :meth:`with_`."""

    url: str = field(default_factory=default_url)
    namespace: str = ""
    keys: str | Path | None = None  # CURVE key directory (stg-keys); None = no security
    key_name: str | None = None  # this client's key in keys/clients/<name>.key_secret
    curve_on_ipc: bool = False  # CURVE on ipc/inproc too (off: file permissions protect ipc)
    lanes: Mapping[str, str] = field(default_factory=dict)  # topic (standard name) -> lane override

    def __post_init__(self):
        for lane in LANES.values():  # the URL, and every endpoint derived from it (ipc path length)
            lane_endpoint(self.url, lane, "out")
        check_namespace(self.namespace)
        lanes = dict(self.lanes)  # a private copy: the caller's dict cannot change us later
        for topic, lane in lanes.items():
            if lane not in LANES:
                raise ValueError(f"lane {lane!r} for topic {topic!r} is not one of {sorted(LANES)}")
        object.__setattr__(self, "lanes", MappingProxyType(lanes))

    def __hash__(self) -> int:
        lanes = tuple(self.lanes.items())
        return hash((self.url, self.namespace, self.keys, self.key_name, self.curve_on_ipc, lanes))

    def __getstate__(self) -> dict:  # a mappingproxy does not pickle; its dict does
        return {**self.__dict__, "lanes": dict(self.lanes)}

    def __setstate__(self, state: dict) -> None:
        for name, value in state.items():
            object.__setattr__(self, name, value)
        object.__setattr__(self, "lanes", MappingProxyType(dict(self.lanes)))

    @classmethod
    def from_env(cls, **overrides) -> BusConfig:
        """Defaults, then STG_BUS / STG_NAMESPACE / STG_BUS_KEYS / STG_BUS_KEY_NAME, then overrides
        (None values in ``overrides`` are ignored, so CLI options can be passed straight in)."""
        values: dict = {}
        env = {
            "url": os.environ.get(ENV_BUS),
            "namespace": os.environ.get(ENV_NAMESPACE),
            "keys": os.environ.get(ENV_KEYS),
            "key_name": os.environ.get(ENV_KEY_NAME),
        }
        values.update({k: v for k, v in env.items() if v})
        values.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**values)

    def with_(self, **changes) -> BusConfig:
        return replace(self, **changes)

    @property
    def transport(self) -> str:
        return parse_url(self.url)[0]

    @property
    def secure(self) -> bool:
        """Whether connections use CURVE: keys given, and tcp (or curve_on_ipc)."""
        return self.keys is not None and (self.transport == "tcp" or self.curve_on_ipc)

    def endpoint(self, lane: str | Lane, side: str) -> str:
        return lane_endpoint(self.url, lane, side)

    def topic(self, name: str) -> str:
        """Full topic for ``name`` in this namespace (a leading '/' skips the namespace)."""
        return join_namespace(self.namespace, name)

    def lane_of(self, topic: str) -> Lane:
        """The lane a full topic travels on: override, else its standard type's lane, else reliable."""
        base = base_name(topic, TOPIC_TYPES)
        key = base or topic
        if key in self.lanes:
            return LANES[self.lanes[key]]
        if base:
            return LANES[TOPIC_TYPES[base].SPEC.lane]
        return LANES[DEFAULT_LANE]

    expected_type = staticmethod(expected_type)


def as_config(config: BusConfig | str | None) -> BusConfig:
    """What the bus classes accept as ``config``: a BusConfig as is, a URL string (the rest from
    the environment), or None (everything from the environment, see :meth:`BusConfig.from_env`)."""
    if config is None:
        return BusConfig.from_env()
    if isinstance(config, str):
        return BusConfig.from_env(url=config)
    return config


def free_tcp_base_port(host: str = "127.0.0.1", span: int = 2 * len(LANES)) -> int:
    """A base port with ``span`` consecutive free ports on ``host``, for a tcp:// bus URL.

    A tcp bus uses two ports per lane from its base port up; this finds a run of them that
    nothing holds right now (tests, benchmarks, a launch on a busy machine).
    """
    for _ in range(200):
        with socket.socket() as probe:
            probe.bind((host, 0))
            base = probe.getsockname()[1]
        if base + span >= 65535:
            continue
        held = []
        try:
            for port in range(base, base + span):
                sock = socket.socket()
                held.append(sock)
                sock.bind((host, port))
            return base
        except OSError:
            continue
        finally:
            for sock in held:
                sock.close()
    raise RuntimeError(f"no run of {span} free tcp ports on {host}")
