"""Socket set-up shared by publishers, subscribers and the broker: options, security, bind/connect,
and the multipart send/receive loops of the hot path with their plain-int zmq flags.

Every socket gets LINGER 0 (closing never waits for unsent messages, so shutdown cannot
hang), the HWMs of its lane, and on the receiving side ZMQ_MAXMSGSIZE, so a peer cannot
make us allocate more than the largest frame any schema allows.

The flags below are the one copy every bus module uses: pyzmq's enum flags cost
microseconds per operation on the hot path, plain ints do not.
"""

from __future__ import annotations

import errno
import os
import socket as pysocket
from pathlib import Path

import zmq

from stg_node.bus import security
from stg_node.bus.config import BusConfig
from stg_node.bus.spec import MAX_FRAME_BYTES, MAX_HEADER_BYTES
from stg_node.bus.topics import Lane

#: Transport cap per frame: the largest buffer plus room for nothing else.
MAX_MESSAGE_BYTES = max(MAX_FRAME_BYTES, MAX_HEADER_BYTES)

# Plain ints, not pyzmq's enums (see the module docstring).
SNDMORE = int(zmq.SNDMORE)
NOBLOCK = int(zmq.NOBLOCK)
EVENTS = int(zmq.EVENTS)
POLLIN = int(zmq.POLLIN)


def send_frames(sock: zmq.Socket, frames: list) -> None:
    """send_multipart(frames, copy=False), minus its per-call flag enum arithmetic."""
    last = len(frames) - 1
    send = sock.send
    for i, frame in enumerate(frames):
        send(frame, SNDMORE if i < last else 0, copy=False)


def recv_multipart(sock: zmq.Socket, flags: int = 0) -> list:
    """recv_multipart(copy=False) without a getsockopt(RCVMORE) per part."""
    frame = sock.recv(flags, copy=False)
    frames = [frame]
    while frame.more:
        frame = sock.recv(0, copy=False)
        frames.append(frame)
    return frames


def make_socket(context: zmq.Context, kind: int, lane: Lane) -> zmq.Socket:
    sock = context.socket(kind)
    sock.linger = 0
    sock.sndhwm = lane.hwm
    sock.rcvhwm = lane.hwm
    if kind in (zmq.SUB, zmq.XSUB):
        sock.maxmsgsize = MAX_MESSAGE_BYTES
    return sock


def ipc_path(endpoint: str) -> Path | None:
    transport, _, address = endpoint.partition("://")
    return Path(address) if transport == "ipc" else None


def ensure_ipc_dir(endpoint: str) -> None:
    """Create the folder of an ipc endpoint (private to the user) before binding."""
    path = ipc_path(endpoint)
    if path is not None and not path.parent.is_dir():
        path.parent.mkdir(parents=True, mode=0o700, exist_ok=True)


def ipc_in_use(endpoint: str) -> bool:
    """True when something accepts connections on this ipc endpoint (e.g. a running broker).

    libzmq silently replaces an ipc socket file on bind; checking first turns a second
    broker on the same path into a clear error instead of a split bus.
    """
    path = ipc_path(endpoint)
    if path is None or not path.exists():
        return False
    probe = pysocket.socket(pysocket.AF_UNIX, pysocket.SOCK_STREAM)
    try:
        probe.settimeout(0.5)
        probe.connect(str(path))
        return True
    except OSError as exc:
        return exc.errno not in (errno.ECONNREFUSED, errno.ENOENT)
    finally:
        probe.close()


def bind(sock: zmq.Socket, endpoint: str, config: BusConfig, secure: bool | None = None) -> None:
    """Bind ``sock``, as a CURVE server when the bus is secure for this transport."""
    secure = _secure_for(endpoint, config) if secure is None else secure
    if secure:
        security.configure_server(sock, config.keys)
        security.ensure_authenticator(sock.context, config.keys)  # running before the bind
    else:
        security.clear_security(sock)
    ensure_ipc_dir(endpoint)
    try:
        sock.bind(endpoint)
    except zmq.ZMQError as exc:
        raise OSError(exc.errno, f"cannot bind {endpoint}: {exc.strerror}") from None
    path = ipc_path(endpoint)
    if path is not None:
        os.chmod(path, 0o600)


def connect(sock: zmq.Socket, endpoint: str, config: BusConfig) -> None:
    """Connect ``sock``, as a CURVE client when the bus is secure for this transport."""
    if _secure_for(endpoint, config):
        security.configure_client(sock, config.keys, config.key_name)
    sock.connect(endpoint)


def _secure_for(endpoint: str, config: BusConfig) -> bool:
    if config.keys is None:
        return False
    return endpoint.startswith("tcp://") or config.curve_on_ipc
