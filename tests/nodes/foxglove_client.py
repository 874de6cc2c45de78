"""A raw client of the published Foxglove WebSocket protocol (github.com/foxglove/ws-protocol,
docs/spec.md), written from the spec with the ``websockets`` package, JSON and Google's protobuf
runtime: nothing of stg_node and nothing of foxglove-sdk, so the tests check the node against
the protocol itself.

- subprotocol ``foxglove.sdk.v1`` (the SDK's name for the same protocol) or ``foxglove.websocket.v1``,
  both offered, as the Foxglove app does; the server sends ``serverInfo`` and ``advertise``
  (JSON: channels with id, topic, encoding, schemaName, schema, schemaEncoding);
- ``subscribe`` (JSON: subscriptions [{id, channelId}]);
- Message Data (binary): opcode 0x01, uint32 subscription id, uint64 log time (ns), payload
  (little-endian); a protobuf payload is decoded with the message class built from the channel's
  schema (a base64 FileDescriptorSet).
"""

from __future__ import annotations

import base64
import contextlib
import json
import struct
import time
from dataclasses import dataclass

SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")
MESSAGE_DATA = 0x01


@dataclass
class Received:
    topic: str
    log_time_ns: int
    payload: bytes
    message: object  # a protobuf message, a dict (json), or None


def protobuf_class(schema_name: str, schema_b64: str):
    """The message class of ``schema_name`` from a base64 FileDescriptorSet (protobuf's own API)."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(schema_b64))
    pool = descriptor_pool.DescriptorPool()
    for file in fds.file:
        pool.Add(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))


class FoxgloveClient:
    """Synchronous client (websockets' sync API): connect, wait for channels, subscribe, receive."""

    def __init__(self, url: str, *, max_queue: int | None = 16, timeout: float = 10.0):
        from websockets.sync.client import connect

        self._stack = contextlib.ExitStack()  # the connection as a context (websockets >= 17.1 wants it)
        deadline = time.monotonic() + timeout
        while True:  # the server may still be starting
            try:
                self.ws = self._stack.enter_context(
                    connect(
                        url,
                        subprotocols=list(SUBPROTOCOLS),
                        max_size=None,
                        max_queue=max_queue,
                        open_timeout=5,
                    )
                )
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        if self.ws.subprotocol not in SUBPROTOCOLS:
            raise AssertionError(f"server chose subprotocol {self.ws.subprotocol!r}")
        self.channels: dict[str, dict] = {}  # topic -> advertised channel
        self.server_info: dict = {}
        self._subs: dict[int, dict] = {}  # subscription id -> channel
        self._classes: dict[int, object] = {}

    def wait_for_channels(self, topics, timeout: float = 30.0) -> None:
        deadline = time.monotonic() + timeout
        while not set(topics) <= set(self.channels):
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"channels {sorted(set(topics) - set(self.channels))} never advertised")
            self._handle(self.ws.recv(timeout=left))

    def subscribe(self, *topics: str) -> None:
        subs = []
        for topic in topics:
            channel = self.channels[topic]
            sub_id = len(self._subs) + 1
            self._subs[sub_id] = channel
            subs.append({"id": sub_id, "channelId": channel["id"]})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def _handle(self, data) -> Received | None:
        if isinstance(data, str):
            msg = json.loads(data)
            if msg.get("op") == "advertise":
                for channel in msg["channels"]:
                    self.channels[channel["topic"]] = channel
            elif msg.get("op") == "serverInfo":
                self.server_info = msg
            return None
        opcode = data[0]
        if opcode != MESSAGE_DATA:
            return None
        sub_id, log_time = struct.unpack_from("<IQ", data, 1)
        payload = bytes(data[13:])
        channel = self._subs[sub_id]
        if channel["encoding"] == "protobuf":
            if sub_id not in self._classes:
                self._classes[sub_id] = protobuf_class(channel["schemaName"], channel["schema"])
            message = self._classes[sub_id].FromString(payload)
        elif channel["encoding"] == "json":
            message = json.loads(payload)
        else:
            message = None
        return Received(channel["topic"], log_time, payload, message)

    def receive(self, timeout: float = 30.0) -> Received:
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError("no message data")
            got = self._handle(self.ws.recv(timeout=left))
            if got is not None:
                return got

    def close(self) -> None:
        self._stack.close()

    def __enter__(self) -> FoxgloveClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
