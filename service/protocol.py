"""Connection-level limits for `python -m service`: uvicorn's httptools protocol with deadlines and caps.

Plain uvicorn lets a connection that never finishes its headers (idle, or one byte a second) live
forever, buffers headers of any size, and accepts connections until file descriptors run out. This
subclass closes a connection whose request headers do not complete within PUSHT_HEADER_TIMEOUT_S,
answers 431 once the unfinished headers exceed PUSHT_MAX_HEADER_BYTES (before buffering more), and
answers 503 at once to connections beyond PUSHT_MAX_CONNECTIONS; a request it cannot parse gets
uvicorn's 400 as JSON, like every other error of the service.
"""

from __future__ import annotations

import asyncio
import json
from typing import Any

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

__all__ = ["ENTRY_POINT", "hardened_protocol"]

ENTRY_POINT = False
"""Set by `python -m service`, so the app can warn when it runs without these limits."""


def _raw_response(status: int, reason: str, detail: str, retry: bool = False) -> bytes:
    body = json.dumps({"detail": detail}).encode()
    head = f"HTTP/1.1 {status} {reason}\r\ncontent-type: application/json\r\ncontent-length: {len(body)}\r\nconnection: close\r\n"
    if retry:
        head += "retry-after: 1\r\n"
    return (head + "\r\n").encode() + body


def hardened_protocol(max_header_bytes: int, header_timeout_s: float, max_connections: int) -> type[HttpToolsProtocol]:
    """A `HardenedProtocol` subclass enforcing these limits, for `uvicorn.Config(http=...)`."""
    limits = {
        "max_header_bytes": max_header_bytes,
        "header_timeout_s": header_timeout_s,
        "max_connections": max_connections,
        "too_big": _raw_response(431, "Request Header Fields Too Large", f"request headers exceed {max_header_bytes} bytes"),
        "too_many": _raw_response(
            503, "Service Unavailable", f"too many open connections (limit {max_connections}); retry later", retry=True
        ),
    }
    return type("HardenedProtocol", (HardenedProtocol,), limits)


class HardenedProtocol(HttpToolsProtocol):
    """httptools with a header deadline, a header size cap and a connection cap (the class attributes, set by
    `hardened_protocol`)."""

    max_header_bytes = 64 * 1024
    header_timeout_s = 10.0
    max_connections = 1024
    too_big = b""
    too_many = b""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._head_bytes = 0
        self._in_head = True
        self._head_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        if len(self.connections) > self.max_connections:
            transport.write(self.too_many)
            transport.close()
            return
        self._arm_head_timer()

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_head_timer()
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        if self._in_head:
            self._head_bytes += len(data)
        super().data_received(data)
        # Checked after parsing, so body bytes that came with complete headers do not count.
        if self._in_head and self._head_bytes > self.max_header_bytes and not self.transport.is_closing():
            self.transport.write(self.too_big)
            self.transport.close()

    def send_400_response(self, msg: str) -> None:
        """uvicorn's answer to bytes that are not HTTP/1.1 (then it closes the connection), with a JSON body."""
        self.transport.write(_raw_response(400, "Bad Request", f"{msg.rstrip('.')}: not a valid HTTP/1.1 request"))
        self.transport.close()

    def on_headers_complete(self) -> None:
        self._in_head = False
        self._cancel_head_timer()
        super().on_headers_complete()

    def on_message_complete(self) -> None:
        super().on_message_complete()
        self._in_head = True  # what follows is the next request's head
        self._head_bytes = 0

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing():
            # The next request's headers (and the rest of an unread body) get the same deadline.
            self._arm_head_timer()

    def _arm_head_timer(self) -> None:
        self._cancel_head_timer()
        self._head_timer = self.loop.call_later(self.header_timeout_s, self._head_timeout)

    def _cancel_head_timer(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _head_timeout(self) -> None:
        self._head_timer = None
        busy = self.cycle is not None and not self.cycle.response_complete  # an app is answering: its own limits apply
        if not busy and not self.transport.is_closing():
            self.transport.close()
