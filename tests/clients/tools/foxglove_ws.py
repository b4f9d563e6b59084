"""A minimal Foxglove WebSocket client for the tests. The protocol is Foxglove's
``foxglove.websocket.v1``; foxglove-sdk servers (0.30 here) name the same protocol
``foxglove.sdk.v1`` in the handshake and refuse a client offering only the old name, so the
client offers both. It
reads the server's advertisements, subscribes to channels by topic, and decodes message data
frames (opcode 1: subscription id u32, log time u64, payload; little-endian), protobuf
payloads with the schema the server advertised (a FileDescriptorSet, base64)."""

from __future__ import annotations

import base64
import json
import struct
import time
from contextlib import ExitStack
from typing import Any

from websockets.sync.client import connect

SUBPROTOCOL = "foxglove.sdk.v1"
LEGACY_SUBPROTOCOL = "foxglove.websocket.v1"


class FoxgloveClient:
    def __init__(self, url: str) -> None:
        self._stack = ExitStack()  # websockets >= 17.1 wants connect() entered as a context
        self.ws = self._stack.enter_context(connect(
            url, subprotocols=[SUBPROTOCOL, LEGACY_SUBPROTOCOL],  # type: ignore[list-item]
            open_timeout=10))
        self.subprotocol = self.ws.subprotocol
        self.channels: dict[str, dict[str, Any]] = {}  # topic -> advertised channel
        self.advertised: list[dict[str, Any]] = []  # every channel advertisement, in order
        self.unadvertised: list[int] = []  # ids the server withdrew
        self.server_info: dict[str, Any] | None = None
        self._subs: dict[int, str] = {}  # subscription id -> topic
        self.messages: dict[str, list[tuple[int, bytes]]] = {}

    def _handle(self, frame: str | bytes) -> None:
        if isinstance(frame, str):
            msg = json.loads(frame)
            if msg.get("op") == "serverInfo":
                self.server_info = msg
            elif msg.get("op") == "advertise":
                self.advertised += msg["channels"]
                for ch in msg["channels"]:
                    self.channels[ch["topic"]] = ch
            elif msg.get("op") == "unadvertise":
                self.unadvertised += msg["channelIds"]
            return
        if frame[0] == 0x01:
            sub_id, log_ns = struct.unpack_from("<IQ", frame, 1)
            topic = self._subs.get(sub_id)
            if topic is not None:
                self.messages.setdefault(topic, []).append((log_ns, bytes(frame[13:])))

    def pump(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            try:
                self._handle(self.ws.recv(timeout=left))
            except TimeoutError:
                return

    def wait_channels(self, topics: list[str], timeout: float = 10.0) -> None:
        end = time.monotonic() + timeout
        while not all(t in self.channels for t in topics):
            assert time.monotonic() < end, f"not advertised: {topics} (have {list(self.channels)})"
            self.pump(0.1)

    def subscribe(self, topics: list[str]) -> None:
        subs = []
        for i, t in enumerate(topics, start=len(self._subs) + 1):
            self._subs[i] = t
            subs.append({"id": i, "channelId": self.channels[t]["id"]})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def protobuf_class(self, topic: str) -> Any:
        return protobuf_message_class(self.channels[topic])

    def close(self) -> None:
        self._stack.close()


def protobuf_message_class(ch: dict[str, Any]) -> Any:
    """The message class of an advertised protobuf channel, from its schema (a
    FileDescriptorSet, base64) and schema name."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    assert ch["encoding"] == "protobuf" and ch["schemaEncoding"] == "protobuf"
    fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(ch["schema"]))
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(ch["schemaName"]))
