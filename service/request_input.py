"""Reading a request safely, and the JSON errors every route answers with.

`read_body` reads under a size limit (413 as soon as it is passed, declared or streamed) and a deadline
(408), with one loop timer for all reads in flight; `check_key` compares the API key in constant time;
`ServiceError` is any problem answered as `{"detail": ...}` with its status, `cap_errors` keeps a 422
short whatever the body.
"""

from __future__ import annotations

import asyncio
import hmac
import json
import weakref
from typing import Any, Awaitable, Callable

from fastapi.responses import Response

__all__ = [
    "MAX_ERRORS",
    "WANTED_HEADERS",
    "ServiceError",
    "cap_errors",
    "check_key",
    "json_error",
    "read_body",
    "request_headers",
]

Scope = dict[str, Any]
Receive = Callable[[], Awaitable[dict[str, Any]]]

MAX_ERRORS = 20
"""Validation errors listed in a 422; the rest are counted, so a body of garbage cannot get a huge answer."""


class ServiceError(Exception):
    """An error answered as JSON `{"detail": ...}` with `status`."""

    def __init__(self, status: int, detail: Any, headers: dict[str, str] | None = None) -> None:
        self.status = status
        self.detail = detail
        self.headers = headers


def json_error(status: int, detail: Any, headers: dict[str, str] | None = None) -> Response:
    """A JSON error response `{"detail": detail}`."""
    return Response(json.dumps({"detail": detail}), status_code=status, media_type="application/json", headers=headers)


def cap_errors(errors: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The first MAX_ERRORS validation errors as {loc, msg, type}, then one entry counting the rest."""
    shown = [
        {"loc": list(e.get("loc", ())), "msg": str(e.get("msg", ""))[:500], "type": e.get("type", "")}
        for e in errors[:MAX_ERRORS]
    ]
    if len(errors) > MAX_ERRORS:
        shown.append({"loc": [], "msg": f"and {len(errors) - MAX_ERRORS} more errors", "type": "too_many_errors"})
    return shown


WANTED_HEADERS = frozenset((b"content-length", b"content-type", b"x-api-key", b"authorization"))
"""The request headers `POST /act` reads."""


def request_headers(scope: Scope, wanted: tuple[bytes, ...] | frozenset[bytes]) -> dict[bytes, str]:
    """The `wanted` request headers (lower-case names) as latin-1 strings."""
    return {name: value.decode("latin-1") for name, value in scope["headers"] if name in wanted}


KEY_HELP = "send it as 'X-API-Key: KEY', 'Authorization: Bearer KEY' or 'Authorization: Api-Key KEY' (openpi-client's)"


def key_matches(headers: dict[bytes, str], expected: bytes) -> bool:
    """The one rule of every route (HTTP and websocket): X-API-Key if sent, else Authorization's Bearer or Api-Key token."""
    given = headers.get(b"x-api-key")
    if given is None:
        scheme, _, token = headers.get(b"authorization", "").partition(" ")
        given = token.strip() if scheme.lower() in ("bearer", "api-key") else None
    return bool(given) and hmac.compare_digest(given.encode("latin-1"), expected)


def check_key(headers: dict[bytes, str], expected: bytes) -> None:
    """Raise 401 unless the headers carry `expected` by `key_matches`' rule."""
    if not key_matches(headers, expected):
        raise ServiceError(401, f"missing or wrong API key: {KEY_HELP}", {"WWW-Authenticate": "Bearer"})


async def read_body(receive: Receive, declared: str | None, limit: int, timeout: float) -> bytes:
    """The body: 413 as soon as it exceeds `limit` bytes, 408 unless all of it arrives within `timeout` seconds."""
    # asyncio.timeout's rules, with one loop timer for every read in flight (_Deadlines): a timer per request, armed
    # and cancelled cold after a model call, costs ~10 us more. A cancellation from elsewhere (shutdown) still
    # propagates as one.
    task = asyncio.current_task()
    cancelling = task.cancelling()
    deadlines = _deadlines(timeout)
    deadlines.add(task)
    try:
        return await _read_body(receive, declared, limit)
    except asyncio.CancelledError:
        if deadlines.expired.pop(task, False) and task.uncancel() <= cancelling:
            raise ServiceError(408, f"the request body took longer than {timeout:g} s to arrive") from None
        raise
    finally:
        deadlines.reads.pop(task, None)


class _Deadlines:
    """The body deadlines of one event loop for one timeout: one timer, at the earliest deadline of the reads in flight.

    Reads are added as they start, so `reads` (insertion-ordered) is in deadline order; a read that ends leaves it. The
    timer cancels every read past its deadline, noting it in `expired` (the cancellation then becomes a 408), and
    re-arms at the next read's deadline: each read is cancelled when its own deadline passes, as with a timer each."""

    __slots__ = ("loop", "timeout", "reads", "expired", "timer")

    def __init__(self, loop: asyncio.AbstractEventLoop, timeout: float) -> None:
        self.loop = loop
        self.timeout = timeout
        self.reads: dict[asyncio.Task, float] = {}
        self.expired: dict[asyncio.Task, bool] = {}
        self.timer: asyncio.TimerHandle | None = None

    def add(self, task: asyncio.Task) -> None:
        deadline = self.loop.time() + self.timeout
        self.reads[task] = deadline
        if self.timer is None:
            self.timer = self.loop.call_at(deadline, self._expire)

    def _expire(self) -> None:
        self.timer = None
        now = self.loop.time()
        late = []
        for task, deadline in self.reads.items():
            if deadline > now:
                self.timer = self.loop.call_at(deadline, self._expire)
                break
            late.append(task)
        for task in late:
            del self.reads[task]
            self.expired[task] = True
            task.cancel()


_deadlines_by_loop: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, dict[float, _Deadlines]] = weakref.WeakKeyDictionary()
_last_deadlines: _Deadlines | None = None


def _deadlines(timeout: float) -> _Deadlines:
    """The running loop's _Deadlines for `timeout` (usually the last one used)."""
    global _last_deadlines
    loop = asyncio.get_running_loop()
    last = _last_deadlines
    if last is not None and last.loop is loop and last.timeout == timeout:
        return last
    by_timeout = _deadlines_by_loop.get(loop)
    if by_timeout is None:
        by_timeout = _deadlines_by_loop[loop] = {}
    deadlines = by_timeout.get(timeout)
    if deadlines is None:
        deadlines = by_timeout[timeout] = _Deadlines(loop, timeout)
    _last_deadlines = deadlines
    return deadlines


# The rest of a refused body is never read: the connection closes after the answer.
_CLOSE = {"Connection": "close"}


async def _read_body(receive: Receive, declared: str | None, limit: int) -> bytes:
    """The body, or 413 as soon as it exceeds `limit` bytes (declared or streamed, e.g. chunked)."""
    if declared is not None:
        if not declared.isdigit():
            raise ServiceError(400, f"invalid Content-Length header {declared!r}", _CLOSE)
        if int(declared) > limit:
            raise ServiceError(413, f"request body of {int(declared)} bytes exceeds the limit of {limit} bytes", _CLOSE)
    chunks = []
    size = 0
    more = True
    while more:
        message = await receive()
        if message["type"] != "http.request":  # http.disconnect: nobody is left to answer
            raise ServiceError(400, "client disconnected before sending the whole body")
        chunk = message.get("body", b"")
        size += len(chunk)
        if size > limit:
            raise ServiceError(413, f"request body exceeds the limit of {limit} bytes", _CLOSE)
        chunks.append(chunk)
        more = message.get("more_body", False)
    return b"".join(chunks)
