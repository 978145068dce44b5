"""`POST /act`, the hot path, answered from the raw ASGI messages.

`ActHandler` checks the key and the content type (415 unless JSON, so a cross-site form post never
reaches a policy), reads the body under a size limit and a deadline (413 / 408 before parsing),
validates it with the strict pydantic request model straight from the JSON bytes (~2 us), runs it
through the policy's batcher while watching for the client hanging up (its queued rows are then
dropped), and serializes with orjson. `ActFastPath`, a plain ASGI wrapper around the whole app, hands `POST /act` to
it before Starlette's middleware and FastAPI's routing (which cost about as much per request as a
batched model call per state); the FastAPI route of the same handler documents it in the OpenAPI
schema and serves it when the router is used without the wrapper.
"""

from __future__ import annotations

import asyncio
import hmac
import json
import logging
import time
from typing import Any, Awaitable, Callable

import numpy as np
import orjson
from fastapi.responses import Response
from pydantic import ValidationError

from service.batching import Batcher, Overloaded
from service.guard import header_bytes, refuse_headers
from service.schemas import act_request_model
from service.settings import Settings
from service.state import ServiceState

__all__ = ["ActFastPath", "ActHandler", "ServiceError", "cap_errors", "check_key", "json_error", "read_body", "request_headers"]

log = logging.getLogger("uvicorn.error")

Scope = dict[str, Any]
Receive = Callable[[], Awaitable[dict[str, Any]]]
Send = Callable[[dict[str, Any]], Awaitable[None]]

MAX_ERRORS = 20
"""Validation errors listed in a 422; the rest are counted, so a body of garbage cannot get a huge answer."""


class ServiceError(Exception):
    """An error answered as JSON `{"detail": ...}` with `status`."""

    def __init__(self, status: int, detail: Any, headers: dict[str, str] | None = None) -> None:
        self.status = status
        self.detail = detail
        self.headers = headers


class ClientGone(Exception):
    """The client hung up while its request waited; nobody is left to answer."""


def json_error(status: int, detail: Any, headers: dict[str, str] | None = None) -> Response:
    """A JSON error response `{"detail": detail}`."""
    return Response(json.dumps({"detail": detail}), status_code=status, media_type="application/json", headers=headers)


def cap_errors(errors: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The first MAX_ERRORS validation errors as {loc, msg, type}, then one entry counting the rest."""
    shown = [{"loc": list(e.get("loc", ())), "msg": str(e.get("msg", ""))[:500], "type": e.get("type", "")} for e in errors[:MAX_ERRORS]]
    if len(errors) > MAX_ERRORS:
        shown.append({"loc": [], "msg": f"and {len(errors) - MAX_ERRORS} more errors", "type": "too_many_errors"})
    return shown


class ActHandler:
    """`POST /act` as a plain function of (service state, ASGI scope, receive) -> (status, JSON bytes, headers)."""

    def __init__(self, settings: Settings) -> None:
        self.request_model = act_request_model(settings.max_states)
        self.max_body = settings.max_body_bytes
        self.body_timeout = settings.body_timeout_s
        self.expected_key = settings.api_key.get_secret_value().encode() if settings.api_key else None

    async def __call__(self, service: ServiceState, scope: Scope, receive: Receive) -> tuple[int, bytes, dict[str, str] | None]:
        """Answer one request; every problem becomes a JSON error with a 4xx/503 status."""
        try:
            return 200, await self._act(service, scope, receive), None
        except ServiceError as exc:
            return exc.status, json.dumps({"detail": exc.detail}).encode(), exc.headers

    async def _act(self, service: ServiceState, scope: Scope, receive: Receive) -> bytes:
        headers = request_headers(scope, (b"content-length", b"content-type", b"x-api-key", b"authorization"))
        if self.expected_key is not None:
            check_key(headers, self.expected_key)
        if not service.ready:
            raise ServiceError(503, "policies are still loading", {"Retry-After": "1"})
        media_type = headers.get(b"content-type", "").partition(";")[0].strip().lower()
        if media_type != "application/json" and not media_type.endswith("+json"):
            raise ServiceError(415, f"the body must be JSON sent as 'Content-Type: application/json', got {media_type or 'none'!r}")
        body = await read_body(receive, headers.get(b"content-length"), self.max_body, self.body_timeout)
        try:
            req = self.request_model.model_validate_json(body)
        except ValidationError as exc:
            raise ServiceError(422, cap_errors(exc.errors(include_url=False, include_input=False, include_context=False))) from None
        batcher = service.batchers.get(req.policy)
        if batcher is None:
            raise ServiceError(404, f"unknown policy {req.policy!r}; loaded policies: {sorted(service.batchers)}")
        policy = batcher.policy
        num_steps = req.num_steps
        if policy.kind != "flow":
            if num_steps is not None:
                raise ServiceError(422, [{"loc": ["num_steps"], "type": "value_error",
                                          "msg": f"policy {req.policy!r} is an {policy.kind} policy: one network pass, no sampler steps; omit num_steps"}])
        elif num_steps is not None:
            problem = policy.check_num_steps(num_steps)
            if problem is not None:
                raise ServiceError(422, [{"loc": ["num_steps"], "msg": problem, "type": "value_error"}])
        single = req.state is not None
        states = np.array([req.state] if single else req.states, dtype=np.float32)
        try:
            future = batcher.enqueue(states, req.seed, num_steps, req.seeds)
        except Overloaded as exc:
            raise ServiceError(503, str(exc), {"Retry-After": "1"}) from None
        actions = await await_actions(future, batcher, receive, len(states))
        payload = {
            "policy": policy.name,
            "kind": policy.kind,
            "backend": policy.backend,
            "actions": np.ascontiguousarray(actions[0] if single else actions),
        }
        # orjson writes float32 arrays directly (shortest float32 repr): ~1 us instead of ~25 us for json.
        return orjson.dumps(payload, option=orjson.OPT_SERIALIZE_NUMPY)


async def await_actions(future: asyncio.Future, batcher: Batcher, receive: Receive, rows: int) -> np.ndarray:
    """The actions of a queued request, every failure as a ServiceError; the rows are dropped if the client hangs up."""
    policy = batcher.policy
    # Watching the connection while a request waits behind real work lets a hang-up drop its rows
    # (a task per request costs ~3 % CPU, so not when the queue is short).
    watcher = asyncio.ensure_future(_drop_when_gone(receive, future, batcher)) if batcher.worth_watching() else None
    try:
        actions = await future
    except ClientGone:
        raise ServiceError(400, "client disconnected before its actions were computed") from None
    except asyncio.CancelledError:  # the server gave up on this request (shutdown): drop its rows too
        future.cancel()
        batcher.purge()
        raise
    except Overloaded as exc:
        raise ServiceError(503, str(exc), {"Retry-After": "1"}) from None
    except Exception as exc:  # a backend failure is our bug, but the client still gets JSON
        log.exception("policy %r failed on %d states", policy.name, rows)
        raise ServiceError(500, f"policy {policy.name!r} failed: {type(exc).__name__}: {exc}") from None
    finally:
        if watcher is not None:
            watcher.cancel()
    if not np.isfinite(actions).all():
        raise ServiceError(500, f"policy {policy.name!r} produced non-finite actions")
    return actions


async def _drop_when_gone(receive: Receive, future: asyncio.Future, batcher: Batcher) -> None:
    """After the body: the next ASGI message is http.disconnect once the client hangs up; drop the request then."""
    while not future.done():
        message = await receive()
        if message["type"] == "http.disconnect":
            if not future.done():
                future.set_exception(ClientGone())
                batcher.purge()
            return


class ActFastPath:
    """ASGI wrapper answering `POST /act` straight from the ASGI messages, before the app's middleware and routing.

    Starlette's error middleware, FastAPI's telemetry hooks, routing and dependency solving cost ~100+ us per request,
    about as much as a batched model call per state; this keeps what /act needs of them (the header limit, the
    request metrics, JSON for an unexpected failure) and hands everything else to the app.
    """

    def __init__(self, app: Callable, handler: ActHandler, metrics: Any, max_header_bytes: int) -> None:
        self.app = app
        self.handler = handler
        self.metrics = metrics
        self.max_header_bytes = max_header_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["path"] != "/act" or scope["method"] != "POST":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = 500  # until an answer is sent
        try:
            size = header_bytes(scope)  # counted inline: an awaited guard coroutine costs more than the count
            if size > self.max_header_bytes:
                await refuse_headers(send, size, self.max_header_bytes)
                status = 431
                return
            try:
                status, body, extra = await self.handler(scope["app"].state.service, scope, receive)
            except Exception as exc:  # our bug; the client still gets JSON
                log.exception("POST /act failed")
                status, body, extra = 500, json.dumps({"detail": f"internal error: {type(exc).__name__}"}).encode(), None
            headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
            if extra:
                headers.extend((k.lower().encode(), v.encode()) for k, v in extra.items())
            await send({"type": "http.response.start", "status": status, "headers": headers})
            await send({"type": "http.response.body", "body": body})
        finally:
            self.metrics.observe_request("/act", "POST", status, time.perf_counter() - start)


def request_headers(scope: Scope, wanted: tuple[bytes, ...]) -> dict[bytes, str]:
    """The `wanted` request headers (lower-case names) as latin-1 strings."""
    return {name: value.decode("latin-1") for name, value in scope["headers"] if name in wanted}


def check_key(headers: dict[bytes, str], expected: bytes) -> None:
    """Raise 401 unless the headers carry `expected` as X-API-Key or a bearer token."""
    given = headers.get(b"x-api-key")
    if given is None:
        scheme, _, token = headers.get(b"authorization", "").partition(" ")
        given = token.strip() if scheme.lower() == "bearer" else None
    if not given or not hmac.compare_digest(given.encode("latin-1"), expected):
        raise ServiceError(
            401, "missing or wrong API key: send it as 'X-API-Key: KEY' or 'Authorization: Bearer KEY'",
            {"WWW-Authenticate": "Bearer"},
        )


async def read_body(receive: Receive, declared: str | None, limit: int, timeout: float) -> bytes:
    """The body: 413 as soon as it exceeds `limit` bytes, 408 unless all of it arrives within `timeout` seconds."""
    # asyncio.timeout's rules with a bare loop timer: its context manager costs ~4 us a request, the timer ~1.5 (/act
    # spends ~40 us outside the model call). A cancellation from elsewhere (shutdown) still propagates as one.
    task = asyncio.current_task()
    cancelling = task.cancelling()
    expired: list[bool] = []
    timer = asyncio.get_running_loop().call_later(timeout, _expire, task, expired)
    try:
        return await _read_body(receive, declared, limit)
    except asyncio.CancelledError:
        if expired and task.uncancel() <= cancelling:
            raise ServiceError(408, f"the request body took longer than {timeout:g} s to arrive") from None
        raise
    finally:
        timer.cancel()


def _expire(task: asyncio.Task, expired: list[bool]) -> None:
    """The body deadline passed: note it (so the cancellation becomes a 408) and cancel the read."""
    expired.append(True)
    task.cancel()


async def _read_body(receive: Receive, declared: str | None, limit: int) -> bytes:
    """The body, or 413 as soon as it exceeds `limit` bytes (declared or streamed, e.g. chunked)."""
    if declared is not None:
        if not declared.isdigit():
            raise ServiceError(400, f"invalid Content-Length header {declared!r}")
        if int(declared) > limit:
            raise ServiceError(413, f"request body of {int(declared)} bytes exceeds the limit of {limit} bytes")
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
            raise ServiceError(413, f"request body exceeds the limit of {limit} bytes")
        chunks.append(chunk)
        more = message.get("more_body", False)
    return b"".join(chunks)
