"""The web node's server: the page (plain files shipped in ``web_static/``) and its live streams
over WebSocket, on one port, in a thread of its own (asyncio, the ``websockets`` package).

Streams are named (``avatar``, ``camera``, ``mask``, ``skeleton``, ``status``); a page subscribes
to the ones it shows. :meth:`WebServer.publish` (thread-safe, called from the node's loop)
hands a stream's newest message to every client that wants it. Nothing queues: each client has
one slot per stream; a message that replaces one its client has not yet taken (the client, or
its network, is slower than the stream) is dropped and counted, per client and in total
(:attr:`WebServer.drops`, which the node reports as NodeStatus drops ``slow_client``). A client's sender
waits on its own socket only (``send`` waits while more than ``write_limit`` bytes are
unsent), so a stalled or vanished client slows nobody; keepalive pings close a dead one.

Wire format, server -> page: binary for images (4-byte big-endian length of a JSON header, the
header, the encoded image), text JSON for the rest; every message names its ``stream``. Page ->
server: JSON ``{"op": "subscribe", "streams": [...]}``, ``{"op": "ping", "t": ms}`` (answered
with ``pong`` and the server's clock, so the page can tell how old a frame is even when the two
clocks differ) and ``{"op": "report", ...}`` (what the page measured: frames shown, frame age),
kept per client for ``/stats.json`` and the operator page.

Access: bound to a loopback address, anyone on this machine may look. Bound elsewhere, a token is
required (:func:`token_policy`: ``STG_WEB_TOKEN``): ``?token=`` on the first page load (answered
with an HttpOnly cookie that the page's other requests and its WebSocket carry), checked in
constant time. Plain HTTP: put TLS in front (a reverse proxy) or use an SSH tunnel beyond a
trusted network.
"""

from __future__ import annotations

import asyncio
import hmac
import ipaddress
import json
import logging
import mimetypes
import os
import struct
import threading
import time
from dataclasses import dataclass, field
from http import HTTPStatus
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

log = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).with_name("web_static")
#: URL path -> file in STATIC_DIR for the pages; other files are served under /static/.
PAGES = {"/": "index.html", "/avatar": "avatar.html"}
WS_PATH = "/ws"
ENV_TOKEN = "STG_WEB_TOKEN"
TOKEN_COOKIE = "stg_web_token"
MIN_TOKEN_CHARS = 16
#: A client's socket may hold this many unsent bytes before its sender waits (then slots drop).
WRITE_LIMIT = 64 * 1024
#: Keepalive: a client that does not answer a ping within PING_TIMEOUT_S is closed.
PING_INTERVAL_S = 5.0
PING_TIMEOUT_S = 10.0
MAX_CLIENT_MESSAGE = 64 * 1024
SECURITY_HEADERS = {
    "Cache-Control": "no-store",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Content-Security-Policy": "default-src 'self'; img-src 'self' blob: data:; connect-src 'self'; "
    "object-src 'none'; base-uri 'none'; frame-ancestors 'none'",
}


class WebServerError(RuntimeError):
    """The server cannot start (address in use, bad host) or a token policy cannot be met."""


def is_loopback(host: str) -> bool:
    """True for addresses only this machine can reach (127.0.0.0/8, ::1, localhost)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def token_policy(host: str, environ=os.environ) -> str | None:
    """The token browsers must give, or None when none is needed.

    Loopback: none, unless ``STG_WEB_TOKEN`` is set (then it is required anyway). Any other
    address: ``STG_WEB_TOKEN`` must be set, at least MIN_TOKEN_CHARS characters."""
    token = environ.get(ENV_TOKEN, "")
    if not token and is_loopback(host):
        return None
    if not token:
        raise WebServerError(
            f"host {host!r} lets other machines in: set {ENV_TOKEN} to a secret of at least "
            f"{MIN_TOKEN_CHARS} characters (e.g. `export {ENV_TOKEN}=$(openssl rand -hex 16)`); browsers "
            "then open http://HOST:PORT/?token=THAT_SECRET"
        )
    if len(token) < MIN_TOKEN_CHARS:
        raise WebServerError(f"{ENV_TOKEN} has {len(token)} characters; use at least {MIN_TOKEN_CHARS}")
    return token


@dataclass
class Client:
    """One connected page: what it wants, its newest unsent message per stream, what it said."""

    id: int
    address: str
    wants: set[str] = field(default_factory=set)
    slots: dict[str, bytes | str] = field(default_factory=dict)
    ready: asyncio.Event = field(default_factory=asyncio.Event)
    sent: int = 0
    drops: int = 0
    report: dict = field(default_factory=dict)
    connected_at: float = field(default_factory=time.time)


def pack_binary(meta: dict, payload: bytes) -> bytes:
    """[uint32 big-endian header length][JSON header][payload]: one binary WebSocket message."""
    head = json.dumps(meta, separators=(",", ":")).encode()
    return struct.pack(">I", len(head)) + head + payload


class WebServer:
    """HTTP pages + WebSocket streams on one port, run in a background thread."""

    def __init__(
        self,
        host: str,
        port: int,
        *,
        token: str | None = None,
        static_dir: Path = STATIC_DIR,
    ):
        self.host = host
        self.port = port
        self.token = token
        self.static_dir = static_dir
        self.static_files = {p.name for p in static_dir.iterdir() if p.is_file()}
        self.clients: dict[int, Client] = {}
        self.drops = 0
        self.sent = 0
        self._wanted: dict[str, int] = {}  # stream -> clients wanting it (read from other threads)
        self._next_id = 1
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server = None
        self._thread: threading.Thread | None = None
        self._stopped = None  # asyncio.Event, set to end the loop

    # -- life cycle (node thread) ---------------------------------------------------------------------

    def start(self, timeout: float = 10.0) -> int:
        """Bind and serve; the port in use (``port`` 0 picks a free one). Raises WebServerError."""
        started = threading.Event()
        failure: list[BaseException] = []

        def run() -> None:
            loop = asyncio.new_event_loop()
            self._loop = loop
            try:
                loop.run_until_complete(self._main(started, failure))
            finally:
                loop.close()

        self._thread = threading.Thread(target=run, name="web-server", daemon=True)
        self._thread.start()
        if not started.wait(timeout):
            raise WebServerError(f"the web server did not start on {self.host}:{self.port} in {timeout} s")
        if failure:
            raise WebServerError(f"cannot serve on {self.host}:{self.port}: {failure[0]}") from failure[0]
        return self.port

    async def _main(self, started: threading.Event, failure: list) -> None:
        from websockets.asyncio.server import serve

        self._stopped = asyncio.Event()
        try:
            self._server = await serve(
                self._connection,
                self.host,
                self.port,
                process_request=self._http,
                compression=None,  # JPEG does not deflate; compressing costs CPU for nothing
                write_limit=WRITE_LIMIT,
                max_size=MAX_CLIENT_MESSAGE,
                max_queue=4,
                ping_interval=PING_INTERVAL_S,
                ping_timeout=PING_TIMEOUT_S,
                server_header="stg_node",
            )
        except OSError as exc:
            failure.append(exc)
            started.set()
            return
        self.port = self._server.sockets[0].getsockname()[1]
        started.set()
        await self._stopped.wait()
        self._server.close()
        await self._server.wait_closed()

    def stop(self, timeout: float = 10.0) -> None:
        if self._loop is not None and self._stopped is not None and not self._loop.is_closed():
            try:
                self._loop.call_soon_threadsafe(self._stopped.set)
            except RuntimeError:  # the loop already ended
                pass
        if self._thread is not None:
            self._thread.join(timeout)

    # -- streams (node thread) ----------------------------------------------------------------------

    def wants(self, stream: str) -> bool:
        """Whether any client wants ``stream`` now (skip the encoding when nobody does)."""
        return self._wanted.get(stream, 0) > 0

    def publish(self, stream: str, meta: dict, payload: bytes | None = None) -> None:
        """Hand ``stream``'s newest message to every client that wants it (thread-safe). With a
        ``payload`` it goes as binary (header + payload), else as JSON text."""
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        meta = {"stream": stream, **meta}
        message: bytes | str = pack_binary(meta, payload) if payload is not None else json.dumps(meta)
        try:
            loop.call_soon_threadsafe(self._deliver, stream, message)
        except RuntimeError:  # stopping
            pass

    def _deliver(self, stream: str, message: bytes | str) -> None:
        dropped = 0
        for client in self.clients.values():
            if stream in client.wants:
                if stream in client.slots:
                    client.drops += 1
                    dropped += 1
                client.slots[stream] = message
                client.ready.set()
        self.drops += dropped

    def stats(self) -> dict:
        """Clients and what they reported (for /stats.json, the operator page and the node's log)."""
        clients = [
            {
                "id": c.id,
                "address": c.address,
                "streams": sorted(c.wants),
                "sent": c.sent,
                "drops": c.drops,
                "connected_s": round(time.time() - c.connected_at, 1),
                "report": c.report,
            }
            for c in list(self.clients.values())
        ]
        return {"clients": clients, "sent": self.sent, "drops": self.drops}

    # -- WebSocket ------------------------------------------------------------------------------------

    async def _connection(self, ws) -> None:
        client = Client(self._next_id, _address(ws))
        self._next_id += 1
        self.clients[client.id] = client
        log.info("page connected: client %d from %s", client.id, client.address)
        sender = asyncio.create_task(self._send_loop(ws, client))
        try:
            async for text in ws:
                if not isinstance(text, str):
                    continue
                try:
                    request = json.loads(text)
                except ValueError:
                    continue
                await self._request(ws, client, request)
        except Exception as exc:  # a broken connection ends this client only
            log.debug("client %d: %s", client.id, exc)
        finally:
            sender.cancel()
            self._set_wants(client, set())
            self.clients.pop(client.id, None)
            log.info(
                "page gone: client %d (%d sent, %d dropped while it lagged)",
                client.id,
                client.sent,
                client.drops,
            )

    async def _request(self, ws, client: Client, request) -> None:
        if not isinstance(request, dict):
            return
        op = request.get("op")
        if op == "subscribe" and isinstance(request.get("streams"), list):
            self._set_wants(client, {str(s) for s in request["streams"]})
        elif op == "ping":
            await ws.send(json.dumps({"stream": "pong", "t": request.get("t"), "server_ns": time.time_ns()}))
        elif op == "report" and isinstance(request.get("report"), dict):
            client.report = request["report"]

    def _set_wants(self, client: Client, wants: set[str]) -> None:
        for stream in client.wants - wants:
            self._wanted[stream] = self._wanted.get(stream, 1) - 1
            client.slots.pop(stream, None)
        for stream in wants - client.wants:
            self._wanted[stream] = self._wanted.get(stream, 0) + 1
        client.wants = wants

    async def _send_loop(self, ws, client: Client) -> None:
        while True:
            await client.ready.wait()
            client.ready.clear()
            while client.slots:
                stream = next(iter(client.slots))
                message = client.slots.pop(stream)
                await ws.send(message)  # waits while this client's socket is full: only it waits
                client.sent += 1
                self.sent += 1

    # -- HTTP -------------------------------------------------------------------------------------------

    def _authorised(self, request, query: dict) -> tuple[bool, bool]:
        """(allowed, set the cookie): a token in the query or the cookie, compared in constant time."""
        if self.token is None:
            return True, False
        given = query.get("token", [""])[0]
        if given and hmac.compare_digest(given.encode(), self.token.encode()):
            return True, True
        cookie = _cookie(request.headers.get("Cookie", ""), TOKEN_COOKIE)
        return bool(cookie) and hmac.compare_digest(cookie.encode(), self.token.encode()), False

    def _http(self, connection, request):
        from websockets.datastructures import Headers
        from websockets.http11 import Response

        url = urlsplit(request.path)
        allowed, set_cookie = self._authorised(request, parse_qs(url.query))
        if not allowed:
            return _response(
                HTTPStatus.UNAUTHORIZED,
                b"stg_node web: a token is required; open this page with ?token=... (the value of "
                + ENV_TOKEN.encode()
                + b" where the web node runs)\n",
                "text/plain; charset=utf-8",
            )
        if url.path == WS_PATH:
            return None  # go on with the WebSocket handshake
        if request.headers.get("Upgrade", "").lower() == "websocket":
            return _response(HTTPStatus.NOT_FOUND, b"the WebSocket is at /ws\n", "text/plain")
        if url.path == "/stats.json":
            body, kind = json.dumps(self.stats()).encode(), "application/json"
        elif url.path in PAGES or (url.path.startswith("/static/") and url.path[8:] in self.static_files):
            name = PAGES.get(url.path) or url.path[8:]
            body = (self.static_dir / name).read_bytes()
            kind = mimetypes.guess_type(name)[0] or "application/octet-stream"
            if kind.startswith("text/") or kind.endswith("javascript"):
                kind += "; charset=utf-8"
        else:
            return _response(HTTPStatus.NOT_FOUND, b"not found\n", "text/plain")
        headers = Headers({**SECURITY_HEADERS, "Content-Type": kind, "Content-Length": str(len(body))})
        if set_cookie:
            headers["Set-Cookie"] = f"{TOKEN_COOKIE}={self.token}; HttpOnly; SameSite=Strict; Path=/"
        return Response(HTTPStatus.OK.value, HTTPStatus.OK.phrase, headers, body)


def _response(status: HTTPStatus, body: bytes, kind: str):
    from websockets.datastructures import Headers
    from websockets.http11 import Response

    headers = Headers({**SECURITY_HEADERS, "Content-Type": kind, "Content-Length": str(len(body))})
    return Response(status.value, status.phrase, headers, body)


def _cookie(header: str, name: str) -> str:
    for part in header.split(";"):
        key, _, value = part.strip().partition("=")
        if key == name:
            return value
    return ""


def _address(ws) -> str:
    try:
        host, port = ws.remote_address[:2]
        return f"{host}:{port}"
    except (TypeError, ValueError, IndexError):
        return "?"
