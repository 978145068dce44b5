"""`POST /act`, the hot path, answered from the raw ASGI messages.

`ActHandler` checks the key and the content type (415 unless JSON, so a cross-site form post never
reaches a policy), reads the body under a size limit and a deadline (413 / 408 before parsing;
`service.request_input`),
validates it (the usual single-state body with orjson and a few checks, `single_state_request`; any
other body with the strict pydantic request model, straight from the JSON bytes), runs it through
the policy's batcher while watching for the client hanging up (its queued rows are then dropped),
and serializes the actions with orjson behind the policy's fixed JSON prefix. `ActFastPath`, a plain
ASGI wrapper around the whole app, hands `POST /act` to it before Starlette's middleware and
FastAPI's routing (which cost about as much per request as a batched model call per state); the
FastAPI route of the same handler documents it in the OpenAPI schema and serves it when the router
is used without the wrapper.

A lone request runs its model call inline, and a model of a few MB evicts the core's caches: the
Python that follows, and the next request's until the model call, runs from L3, ~10x slower than in
a warm microbenchmark (measured in process with the 8.8 MB flow student: ~210 us of path around the
model call, against ~40 us with a stub model). So the path drops whole pieces of machinery rather
than microseconds: one timer for all body deadlines of a loop instead of a timer per request, metrics
appended to a buffer, a non-finite check that reads the serialized bytes, no pydantic for the usual body.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
import types
from typing import Any, Awaitable, Callable, Generator

import numpy as np
import orjson
from pydantic import ValidationError

from pusht.spec import STATE_DIM
from service.batching import Batcher, Overloaded
from service.guard import refuse_headers
from service.request_input import WANTED_HEADERS, Receive, Scope, ServiceError, cap_errors, check_key, read_body, request_headers
from service.schemas import MAX_SEED, act_request_model
from service.settings import MAX_NUM_STEPS, STATE_LIMIT, Settings
from service.state import ServiceState

__all__ = ["ActFastPath", "ActHandler", "ClientGone", "await_actions", "single_state_request"]

log = logging.getLogger("uvicorn.error")

Send = Callable[[dict[str, Any]], Awaitable[None]]


class ClientGone(Exception):
    """The client hung up while its request waited; nobody is left to answer."""


class ActHandler:
    """`POST /act` as a plain function of (service state, ASGI scope, receive) -> (status, JSON bytes, headers)."""

    def __init__(self, settings: Settings) -> None:
        self.request_model = act_request_model(settings.max_states)
        self.max_body = settings.max_body_bytes
        self.body_timeout = settings.body_timeout_s
        self.expected_key = settings.api_key.get_secret_value().encode() if settings.api_key else None
        self._prefixes: dict[Any, bytes] = {}  # by policy object

    async def __call__(
        self, service: ServiceState, scope: Scope, receive: Receive, headers: dict[bytes, str] | None = None
    ) -> tuple[int, bytes, dict[str, str] | None]:
        """Answer one request (`headers`: its WANTED_HEADERS, if already picked); every problem becomes a JSON error with a 4xx/503 status."""
        try:
            return 200, await self._act(service, scope, receive, headers), None
        except ServiceError as exc:
            return exc.status, json.dumps({"detail": exc.detail}).encode(), exc.headers

    async def _act(self, service: ServiceState, scope: Scope, receive: Receive, headers: dict[bytes, str] | None) -> bytes:
        if headers is None:
            headers = request_headers(scope, WANTED_HEADERS)
        if self.expected_key is not None:
            check_key(headers, self.expected_key)
        if not service.ready:
            raise ServiceError(503, "policies are still loading", {"Retry-After": "1"})
        media_type = headers.get(b"content-type", "").partition(";")[0].strip().lower()
        if media_type != "application/json" and not media_type.endswith("+json"):
            raise ServiceError(
                415, f"the body must be JSON sent as 'Content-Type: application/json', got {media_type or 'none'!r}"
            )
        body = await read_body(receive, headers.get(b"content-length"), self.max_body, self.body_timeout)
        # Each body is parsed once: one that cannot be the usual single state goes straight to the model.
        fields = None if len(body) > SINGLE_STATE_MAX_BYTES or b'"states"' in body else single_state_request(body)
        if fields is not None:
            name, state, seed, num_steps = fields
            seeds = rows = None
        else:
            try:
                req = self.request_model.model_validate_json(body)
            except ValidationError as exc:
                raise ServiceError(
                    422, cap_errors(exc.errors(include_url=False, include_input=False, include_context=False))
                ) from None
            name, state, seed, num_steps, rows, seeds = req.policy, req.state, req.seed, req.num_steps, req.states, req.seeds
        name = name if name is not None else service.default_policy
        batcher = service.batchers.get(name)
        if batcher is None:
            raise ServiceError(404, f"unknown policy {name!r}; loaded policies: {sorted(service.batchers)}")
        policy = batcher.policy
        if policy.kind != "flow":
            if num_steps is not None:
                raise ServiceError(
                    422,
                    [
                        {
                            "loc": ["num_steps"],
                            "type": "value_error",
                            "msg": f"policy {name!r} is an {policy.kind} policy: one network pass, no sampler steps; omit num_steps",
                        }
                    ],
                )
        elif num_steps is not None:
            problem = policy.check_num_steps(num_steps)
            if problem is not None:
                raise ServiceError(422, [{"loc": ["num_steps"], "msg": problem, "type": "value_error"}])
        single = state is not None
        states = np.array([state] if single else rows, dtype=np.float32)
        try:
            future = batcher.enqueue(states, seed, num_steps, seeds)
        except Overloaded as exc:
            raise ServiceError(503, str(exc), {"Retry-After": "1"}) from None
        actions = await await_actions(future, batcher, receive, len(states), check_finite=False)
        return await self._response(policy, actions[0] if single else actions)

    async def _response(self, policy: Any, actions: np.ndarray) -> bytes:
        """The 200 body: the policy's fixed `{"policy":..,"kind":..,"backend":..,"actions":` prefix, then the actions.

        orjson writes float32 arrays directly (shortest float32 repr) and a non-finite value as `null`, so a search
        of the array's bytes is the finiteness check (numpy's isfinite + all, run cold, cost ~10 us more)."""
        prefix = self._prefixes.get(policy)
        if prefix is None:
            head = orjson.dumps({"policy": policy.name, "kind": policy.kind, "backend": policy.backend})
            prefix = self._prefixes[policy] = head[:-1] + b',"actions":'
        array = await _actions_json(actions)
        if b"null" in array:
            raise ServiceError(500, f"policy {policy.name!r} produced non-finite actions")
        return prefix + array + b"}"


ROWS_PER_SLICE = 64
"""rows of a batched answer serialized between two turns of the event loop (about 0.1 ms of orjson each)"""


async def _actions_json(actions: np.ndarray) -> bytes:
    """orjson's bytes of `actions`; a large batch slice by slice, letting the loop serve other requests in between (a
    512-row answer is ~0.6 ms of float formatting, which a lone row beside bulk clients would otherwise wait behind)."""
    if actions.ndim < 3 or len(actions) <= ROWS_PER_SLICE:
        return _dumps(actions)
    parts = []
    for start in range(0, len(actions), ROWS_PER_SLICE):
        parts.append(_dumps(actions[start : start + ROWS_PER_SLICE])[1:-1])
        await asyncio.sleep(0)
    return b"[" + b",".join(parts) + b"]"


def _dumps(array: np.ndarray) -> bytes:
    try:
        return orjson.dumps(array, option=orjson.OPT_SERIALIZE_NUMPY)
    except TypeError:  # not C-contiguous
        return orjson.dumps(np.ascontiguousarray(array), option=orjson.OPT_SERIALIZE_NUMPY)


_SINGLE_STATE_KEYS = frozenset(("policy", "state", "seed", "num_steps"))
SINGLE_STATE_MAX_BYTES = 1024
"""bodies longer than this skip `single_state_request` (a usual single-state body is about 100 bytes): the model parses them"""


def single_state_request(body: bytes) -> tuple[str | None, list, int | None, int | None] | None:
    """(policy, state, seed, num_steps) of a valid body of the usual shape, `{["policy",] "state"[, "seed"][, "num_steps"]}`;
    None for any other body, which the pydantic request model then accepts or answers with its errors.

    It accepts exactly what the model accepts for that shape (numbers as JSON numbers, finite and within +-STATE_LIMIT,
    integer seed and num_steps in range, last duplicate key wins), with orjson and a few checks: the model, cold after a
    model call, costs ~15 us more per request. `state` keeps JSON's ints, which become the same float32."""
    try:
        data = orjson.loads(body)  # no NaN or Infinity tokens, nor overflowing literals: those go to the model
    except orjson.JSONDecodeError:
        return None
    if type(data) is not dict or not _SINGLE_STATE_KEYS.issuperset(data):
        return None
    policy, state, seed, num_steps = data.get("policy"), data.get("state"), data.get("seed"), data.get("num_steps")
    if (
        (policy is not None and (type(policy) is not str or not 0 < len(policy) <= 200))
        or type(state) is not list
        or len(state) != STATE_DIM
    ):
        return None
    for value in state:  # a bool is an int to Python, not to the model
        if (type(value) is not float and type(value) is not int) or not -STATE_LIMIT <= value <= STATE_LIMIT:
            return None
    if seed is not None and (type(seed) is not int or not 0 <= seed <= MAX_SEED):
        return None
    if num_steps is not None and (type(num_steps) is not int or not 1 <= num_steps <= MAX_NUM_STEPS):
        return None
    return policy, state, seed, num_steps


async def await_actions(
    future: asyncio.Future, batcher: Batcher, receive: Receive, rows: int, check_finite: bool = True
) -> np.ndarray:
    """The actions of a queued request, every failure as a ServiceError; the rows are dropped if the client hangs up.

    `check_finite`: a 500 for non-finite actions (False: the caller checks them itself)."""
    policy = batcher.policy
    watcher = None
    try:
        if batcher.runs_alone():
            # Its call, already scheduled, runs inline next iteration, before this task's next step: resumed then, the
            # request finds its actions ready, one loop iteration (~15 us, cold) sooner than woken by the future.
            await _one_iteration()
        # Watching the connection while a request waits behind real work lets a hang-up drop its rows
        # (a task per request costs ~3 % CPU, so not when the queue is short).
        if not future.done() and batcher.worth_watching():
            watcher = asyncio.ensure_future(_drop_when_gone(receive, future, batcher))
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
    if check_finite and not np.isfinite(actions).all():
        raise ServiceError(500, f"policy {policy.name!r} produced non-finite actions")
    return actions


@types.coroutine
def _one_iteration() -> Generator[None, None, None]:
    """Yield to the event loop for one iteration (asyncio.sleep(0) without its frame)."""
    yield


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
            # One pass over the headers counts them (as guard.header_bytes: an awaited guard coroutine costs more than
            # the count) and picks the handler's.
            size = len(scope.get("raw_path") or b"") + len(scope.get("query_string") or b"")
            headers = {}
            for name, value in scope["headers"]:
                size += len(name) + len(value) + 4
                if name in WANTED_HEADERS:
                    headers[name] = value.decode("latin-1")
            if size > self.max_header_bytes:
                await refuse_headers(send, size, self.max_header_bytes)
                status = 431
                return
            try:
                status, body, extra = await self.handler(scope["app"].state.service, scope, receive, headers)
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
