"""A minimal client of the Foxglove WebSocket protocol, version 1 (subprotocol
`foxglove.sdk.v1`), for the tests of `hostsim run --live` and scripts/bench-live.py.

What a viewer does: the WebSocket handshake with the subprotocol, the server's `serverInfo`
and `advertise` (JSON text messages), `subscribe` to channels by id, then `messageData`
(binary, opcode 1: subscription id u32 LE, log time u64 LE, the message's bytes); and what
a Parameters panel does: `getParameters` and `setParameters`, answered by `parameterValues`. The
specification: https://github.com/foxglove/ws-protocol/blob/main/docs/spec.md.

`FoxgloveClient` reads with the `websockets` package; `StalledClient` speaks the handshake
and one subscription over a bare socket with a small receive buffer, then never reads again,
as a viewer on a stuck network would.
"""

from __future__ import annotations

import base64
import contextlib
import json
import os
import socket
import struct
import time
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import urlparse

from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect
from websockets.typing import Subprotocol

SUBPROTOCOL = "foxglove.sdk.v1"

#: Binary opcode of a server's messageData.
MESSAGE_DATA = 1


@dataclass
class MessageData:
    """One message of a subscription, as the server sent it."""

    subscription: int
    log_time: int
    data: bytes


def parse_message_data(frame: bytes) -> MessageData:
    """A binary server message; only messageData is expected of a log's server."""
    assert frame[0] == MESSAGE_DATA, f"binary opcode {frame[0]}"
    subscription, log_time = struct.unpack_from("<IQ", frame, 1)
    return MessageData(subscription, log_time, bytes(frame[13:]))


@dataclass
class FoxgloveClient:
    """A connected client: `server_info` and `channels` (id -> the advertised channel) once
    `start` has read them."""

    url: str
    subprotocols: tuple[str, ...] = (SUBPROTOCOL,)
    server_info: dict[str, Any] = field(default_factory=dict)
    channels: dict[int, dict[str, Any]] = field(default_factory=dict)
    statuses: list[dict[str, Any]] = field(default_factory=list)
    subscriptions: dict[int, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        # Entered as a context manager (websockets 17.1 deprecates a bare connection); `close`
        # leaves it.
        self._stack = contextlib.ExitStack()
        self.ws = self._stack.enter_context(connect(
            self.url, subprotocols=[Subprotocol(p) for p in self.subprotocols], open_timeout=10,
            max_size=None, compression=None))

    @property
    def subprotocol(self) -> str | None:
        return self.ws.subprotocol

    def start(self, timeout: float = 10.0) -> None:
        """Reads `serverInfo` (the server's first message) and the channels' `advertise`."""
        first = self.recv(timeout)
        assert isinstance(first, dict) and first.get("op") == "serverInfo", first
        self.server_info = first
        while not self.channels:
            self.recv(timeout)

    def recv(self, timeout: float | None = None) -> dict[str, Any] | MessageData:
        """The next server message: a JSON one as a dict (`advertise` and `status` are kept
        too), a binary one as `MessageData`. Raises TimeoutError, or ConnectionClosed once
        the server has closed."""
        raw = self.ws.recv(timeout=timeout)
        if isinstance(raw, bytes):
            return parse_message_data(raw)
        msg: dict[str, Any] = json.loads(raw)
        if msg.get("op") == "advertise":
            for c in msg["channels"]:
                self.channels[c["id"]] = c
        elif msg.get("op") == "status":
            self.statuses.append(msg)
        return msg

    def subscribe(self, topics: list[str] | None = None) -> dict[int, str]:
        """Subscribes to `topics` (all channels if None); returns subscription id -> topic."""
        by_topic = {c["topic"]: cid for cid, c in self.channels.items()}
        wanted = list(by_topic) if topics is None else topics
        subs = []
        for topic in wanted:
            sub_id = len(self.subscriptions) + 1
            self.subscriptions[sub_id] = topic
            subs.append({"id": sub_id, "channelId": by_topic[topic]})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
        return dict(self.subscriptions)

    def parameters(self, op: str, request_id: str, timeout: float = 10.0,
                   **fields: Any) -> tuple[dict[str, Any], list[dict[str, Any]]]:
        """Sends a `getParameters` or `setParameters` request (`fields`: `parameterNames`,
        `parameters`); returns its answer's values by name and the statuses the server sent
        before it (its refusals: a server sends them first)."""
        before = len(self.statuses)
        self.ws.send(json.dumps({"op": op, "id": request_id, **fields}))
        deadline = time.monotonic() + timeout
        while True:
            m = self.recv(max(0.0, deadline - time.monotonic()))
            if isinstance(m, dict) and m.get("op") == "parameterValues" and m.get("id") == request_id:
                values = {p["name"]: p.get("value") for p in m["parameters"]}
                return values, self.statuses[before:]

    def read_until_closed(self, timeout: float = 30.0) -> list[tuple[str, MessageData, float]]:
        """Every message until the server closes: (topic, message, wall-clock time received)."""
        out: list[tuple[str, MessageData, float]] = []
        deadline = time.monotonic() + timeout
        while True:
            try:
                m = self.recv(max(0.0, deadline - time.monotonic()))
            except ConnectionClosed:
                return out
            if isinstance(m, MessageData):
                out.append((self.subscriptions[m.subscription], m, time.monotonic()))

    def close(self) -> None:
        self._stack.close()


class StalledClient:
    """Connects with a small receive buffer, subscribes to every channel, then reads nothing:
    what the server writes piles up in its queue for this client."""

    def __init__(self, url: str, rcvbuf: int = 4096, timeout: float = 10.0) -> None:
        u = urlparse(url)
        host, port = u.hostname or "127.0.0.1", u.port or 8765
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.sock.settimeout(timeout)
        self.sock.connect((host, port))
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET / HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\n"
                           f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                           f"Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: {SUBPROTOCOL}\r\n\r\n").encode())
        self.buf = b""
        while b"\r\n\r\n" not in self.buf:
            self.buf += self._read()
        head, self.buf = self.buf.split(b"\r\n\r\n", 1)
        assert head.startswith(b"HTTP/1.1 101"), head
        channels: list[dict[str, Any]] = []
        while not channels:
            msg = json.loads(self._frame())
            if msg.get("op") == "advertise":
                channels = msg["channels"]
        subs = [{"id": i + 1, "channelId": c["id"]} for i, c in enumerate(channels)]
        self._send_text(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def _read(self) -> bytes:
        chunk = self.sock.recv(65536)
        if not chunk:
            raise ConnectionError("closed during the handshake")
        return chunk

    def _frame(self) -> bytes:
        """The next (unmasked, unfragmented) frame's payload."""
        while len(self.buf) < 2:
            self.buf += self._read()
        n, at = self.buf[1] & 0x7F, 2
        if n == 126:
            while len(self.buf) < 4:
                self.buf += self._read()
            n, at = struct.unpack_from(">H", self.buf, 2)[0], 4
        elif n == 127:
            while len(self.buf) < 10:
                self.buf += self._read()
            n, at = struct.unpack_from(">Q", self.buf, 2)[0], 10
        while len(self.buf) < at + n:
            self.buf += self._read()
        payload, self.buf = self.buf[at:at + n], self.buf[at + n:]
        return payload

    def _send_text(self, text: str) -> None:
        data = text.encode()
        mask = os.urandom(4)
        header = bytes([0x81])
        if len(data) < 126:
            header += bytes([0x80 | len(data)])
        else:
            header += bytes([0x80 | 126]) + struct.pack(">H", len(data))
        self.sock.sendall(header + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))

    def close(self) -> None:
        self.sock.close()
