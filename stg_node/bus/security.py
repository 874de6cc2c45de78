"""CURVE keys and their use on sockets: authentication and encryption for tcp endpoints.

A key directory (made by ``stg-keys init``) holds::

    server.key            the broker's public key: every client needs a copy
    server.key_secret     the broker's secret key: only on the broker's machine (mode 0600)
    authorized/NAME.key   public keys of the clients the broker lets in
    clients/NAME.key_secret, clients/NAME.key
                          a client's key pair (``stg-keys add NAME``); copy server.key and
                          clients/NAME.key_secret, in this layout, to that client's machine

The side that binds (the broker, or a publisher with ``bind=True``) is the CURVE server
and runs a ZAP authenticator (zmq.auth) that admits exactly the keys in ``authorized/``.
Connecting sides are CURVE clients. An unauthorised peer completes no handshake, so it
receives nothing and nothing it sends is accepted. Keys are read when a socket is set
up: after ``stg-keys revoke``, restart the broker.
"""

from __future__ import annotations

import logging
import os
import threading
import weakref
from pathlib import Path

import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator

log = logging.getLogger(__name__)

SERVER_NAME = "server"
AUTHORIZED_DIR = "authorized"
CLIENTS_DIR = "clients"
ZAP_DOMAIN = "stg"


class MissingKeyError(FileNotFoundError):
    """A key file the configuration needs is missing."""


def _need(path: Path, what: str) -> Path:
    if not path.is_file():
        raise MissingKeyError(
            f"{what} not found: {path} (make keys with `stg-keys init DIR` / `stg-keys add DIR NAME`)"
        )
    return path


def check_key_name(name: str) -> str:
    """``name`` if it can name a client key (a file name in authorized/), else ValueError."""
    if not name or not all(c.isalnum() or c in "-_." for c in name) or name.startswith("."):
        raise ValueError(f"key name {name!r} must be letters, digits, '-', '_' or '.'")
    if name == SERVER_NAME:
        raise ValueError(f"{SERVER_NAME!r} is the broker's own key name")
    return name


def _private(path: str | Path) -> None:
    os.chmod(path, 0o600)


def init_keys(directory: str | Path, *, force: bool = False) -> Path:
    """Create a key directory with the broker's key pair and an empty authorized/ list."""
    root = Path(directory)
    root.mkdir(parents=True, exist_ok=True)
    (root / AUTHORIZED_DIR).mkdir(exist_ok=True)
    (root / CLIENTS_DIR).mkdir(exist_ok=True)
    secret = root / f"{SERVER_NAME}.key_secret"
    if secret.exists() and not force:
        raise FileExistsError(f"{secret} exists; pass force=True (--force) to replace the broker's keys")
    _, secret_file = zmq.auth.create_certificates(root, SERVER_NAME)
    _private(secret_file)
    return root


def add_client(directory: str | Path, name: str) -> Path:
    """Make a client key pair under clients/ and authorise it; returns the secret key file."""
    root = Path(directory)
    _need(root / f"{SERVER_NAME}.key", "broker public key")
    check_key_name(name)
    clients = root / CLIENTS_DIR
    clients.mkdir(exist_ok=True)
    if (clients / f"{name}.key_secret").exists():
        raise FileExistsError(f"client {name!r} already has keys in {clients}")
    public_file, secret_file = zmq.auth.create_certificates(clients, name)
    _private(secret_file)
    authorize(root, public_file)
    return Path(secret_file)


def authorize(directory: str | Path, public_key_file: str | Path) -> Path:
    """Let the holder of ``public_key_file``'s secret key in (copies it into authorized/)."""
    root = Path(directory)
    src = _need(Path(public_key_file), "public key file")
    zmq.auth.load_certificate(src)  # refuse anything that is not a key file
    dest = root / AUTHORIZED_DIR / (src.name if src.name.endswith(".key") else src.name + ".key")
    dest.parent.mkdir(exist_ok=True)
    dest.write_bytes(src.read_bytes())
    return dest


def revoke(directory: str | Path, name: str) -> bool:
    """Remove ``name`` from authorized/ (its key files stay). True if it was authorised."""
    path = Path(directory) / AUTHORIZED_DIR / f"{check_key_name(name)}.key"
    if path.exists():
        path.unlink()
        return True
    return False


def authorized_names(directory: str | Path) -> list[str]:
    folder = Path(directory) / AUTHORIZED_DIR
    return sorted(p.stem for p in folder.glob("*.key")) if folder.is_dir() else []


def server_public_key(directory: str | Path) -> bytes:
    public, _ = zmq.auth.load_certificate(_need(Path(directory) / f"{SERVER_NAME}.key", "broker public key"))
    return public


def configure_server(sock: zmq.Socket, directory: str | Path) -> None:
    """Make the next bind of ``sock`` a CURVE server with the broker's secret key."""
    public, secret = zmq.auth.load_certificate(
        _need(Path(directory) / f"{SERVER_NAME}.key_secret", "broker secret key")
    )
    sock.curve_secretkey = secret
    sock.curve_publickey = public
    sock.zap_domain = ZAP_DOMAIN.encode()
    sock.curve_server = True


def configure_client(sock: zmq.Socket, directory: str | Path, name: str | None) -> None:
    """Make the next connect of ``sock`` a CURVE client with key ``name`` (clients/NAME.key_secret)."""
    if not name:
        raise ValueError(
            "a CURVE client needs a key name (BusConfig.key_name / --key-name / STG_BUS_KEY_NAME)"
        )
    root = Path(directory)
    secret_file = root / CLIENTS_DIR / f"{name}.key_secret"
    if not secret_file.is_file() and (root / f"{name}.key_secret").is_file():
        secret_file = root / f"{name}.key_secret"
    public, secret = zmq.auth.load_certificate(_need(secret_file, f"secret key of client {name!r}"))
    if secret is None:
        raise MissingKeyError(f"{secret_file} holds no secret key")
    sock.curve_secretkey = secret
    sock.curve_publickey = public
    sock.curve_serverkey = server_public_key(root)


def clear_security(sock: zmq.Socket) -> None:
    """Back to the NULL mechanism for the next bind/connect (e.g. ipc next to a CURVE tcp bind).

    The ZAP domain may stay set: the authenticator admits NULL-mechanism peers (no keys to
    check); ipc is protected by the socket file's permissions (0600)."""
    if sock.curve_server:
        sock.curve_server = False


_authenticators: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_auth_lock = threading.Lock()


def ensure_authenticator(context: zmq.Context, directory: str | Path) -> ThreadAuthenticator:
    """The context's ZAP authenticator admitting keys in ``directory``/authorized (one per context)."""
    authorized = Path(directory) / AUTHORIZED_DIR
    if not authorized.is_dir():
        raise MissingKeyError(f"authorized-keys folder not found: {authorized} (run `stg-keys init`)")
    with _auth_lock:
        auth = _authenticators.get(context)
        if auth is None:
            auth = ThreadAuthenticator(context, log=logging.getLogger("stg_node.bus.zap"))
            auth.start()
            _authenticators[context] = auth
        auth.configure_curve(domain=ZAP_DOMAIN, location=str(authorized))  # "*" only means "no domain"
        log.debug(
            "CURVE authenticator admits %d key(s) from %s", len(authorized_names(directory)), authorized
        )
        return auth


def stop_authenticator(context: zmq.Context) -> None:
    with _auth_lock:
        auth = _authenticators.pop(context, None)
    if auth is not None:
        auth.stop()
