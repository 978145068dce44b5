"""ASGI-level protections that hold however the app is started, even as plain `uvicorn service.app:app`.

`HeaderLimit` answers 431 to a request whose line and headers exceed PUSHT_MAX_HEADER_BYTES (the
server has buffered them by then: `python -m service` also bounds them before buffering).
`QuietStartupFailure` turns a startup refusal into uvicorn's one-line error instead of a traceback,
and `Refusal` is the app that a bad `PUSHT_*` setting leaves: it fails startup naming the variable.
"""

from __future__ import annotations

import json
from typing import Any, Awaitable, Callable

__all__ = [
    "HeaderLimit",
    "QuietStartupFailure",
    "Refusal",
    "StartupProblem",
    "header_bytes",
    "refuse_headers",
    "refuse_large_headers",
]

Scope = dict[str, Any]
Receive = Callable[[], Awaitable[dict[str, Any]]]
Send = Callable[[dict[str, Any]], Awaitable[None]]


class StartupProblem(RuntimeError):
    """A configuration problem that stops startup; the message says what and where."""


class HeaderLimit:
    """431 (and close) for a request whose path, query and headers add up to more than `max_bytes`."""

    def __init__(self, app: Callable, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or not await refuse_large_headers(scope, send, self.max_bytes):
            await self.app(scope, receive, send)


async def refuse_large_headers(scope: Scope, send: Send, max_bytes: int) -> bool:
    """Answer 431 (and close) if the request's path, query and headers add up to more than `max_bytes`; True if it did."""
    size = header_bytes(scope)
    if size <= max_bytes:
        return False
    await refuse_headers(send, size, max_bytes)
    return True


def header_bytes(scope: Scope) -> int:
    """The bytes of the request's path, query and headers, as counted against PUSHT_MAX_HEADER_BYTES."""
    size = len(scope.get("raw_path") or b"") + len(scope.get("query_string") or b"")
    for name, value in scope["headers"]:
        size += len(name) + len(value) + 4
    return size


async def refuse_headers(send: Send, size: int, max_bytes: int) -> None:
    """Answer 431 (and close) to a request whose path, query and headers are `size` bytes, over `max_bytes`."""
    body = json.dumps({"detail": f"request headers of {size} bytes exceed the limit of {max_bytes} bytes"}).encode()
    await send(
        {
            "type": "http.response.start",
            "status": 431,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
                (b"connection", b"close"),
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})


class QuietStartupFailure:
    """Lifespan: when startup stops on a StartupProblem-like error, uvicorn logs its one line, not a traceback."""

    def __init__(self, app: Callable, problems: list[str]) -> None:
        self.app = app
        self.problems = problems  # the lifespan appends the line before it raises

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "lifespan":
            await self.app(scope, receive, send)
            return

        async def quiet_send(message: dict[str, Any]) -> None:
            if message["type"] == "lifespan.startup.failed" and self.problems:
                message = {**message, "message": f"cannot start: {self.problems[-1]}"}
            await send(message)

        await self.app(scope, receive, quiet_send)


class Refusal:
    """The app left by a bad setting: its startup fails with the one-line `message`; requests get 503."""

    def __init__(self, message: str) -> None:
        self.message = message

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "lifespan":
            await receive()
            await send({"type": "lifespan.startup.failed", "message": f"cannot start: {self.message}"})
            return
        if scope["type"] == "http":
            body = json.dumps({"detail": f"misconfigured: {self.message}"}).encode()
            await send({"type": "http.response.start", "status": 503, "headers": [(b"content-type", b"application/json")]})
            await send({"type": "http.response.body", "body": body})
