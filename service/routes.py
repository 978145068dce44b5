"""HTTP routes: `POST /act`, `GET /policies`, `/healthz`, `/readyz`, `/metrics`.

`POST /act` is the hot path. `ActHandler` answers it from the raw ASGI messages: the body is read
under a size limit (413 before parsing), validated by the strict pydantic request model straight
from the JSON bytes (~2 us), run through the policy's batcher, and serialized with orjson.
`ActFastPath`, a plain ASGI middleware, hands `POST /act` to it before FastAPI's routing and
dependency machinery (which costs about as much per request as a batched model call per state);
the FastAPI route of the same handler documents it in the OpenAPI schema and serves it when the
router is used without the middleware.
"""

from __future__ import annotations

import hmac
import json
import logging
from typing import Any, Awaitable, Callable

import numpy as np
import orjson
from fastapi import APIRouter, Request, Security
from fastapi.responses import Response
from fastapi.security import APIKeyHeader, HTTPAuthorizationCredentials, HTTPBearer
from pydantic import ValidationError

from service.batching import Overloaded
from service.metrics import CONTENT_TYPE_LATEST
from service.schemas import (
    ActResponse,
    ErrorResponse,
    PoliciesResponse,
    PolicyInfo,
    act_request_model,
)
from service.settings import Settings
from service.state import ServiceState

__all__ = ["ActFastPath", "ActHandler", "ServiceError", "json_error", "make_router"]

log = logging.getLogger("uvicorn.error")

Scope = dict[str, Any]
Receive = Callable[[], Awaitable[dict[str, Any]]]
Send = Callable[[dict[str, Any]], Awaitable[None]]

_api_key_header = APIKeyHeader(name="X-API-Key", auto_error=False, description="the PUSHT_API_KEY, when the service sets one")
_bearer = HTTPBearer(auto_error=False, description="the PUSHT_API_KEY as a bearer token, when the service sets one")


class ServiceError(Exception):
    """An error answered as JSON `{"detail": ...}` with `status`."""

    def __init__(self, status: int, detail: Any, headers: dict[str, str] | None = None) -> None:
        self.status = status
        self.detail = detail
        self.headers = headers


def json_error(status: int, detail: Any, headers: dict[str, str] | None = None) -> Response:
    """A JSON error response `{"detail": detail}`."""
    return Response(json.dumps({"detail": detail}), status_code=status, media_type="application/json", headers=headers)


def make_router(settings: Settings, handler: "ActHandler | None" = None) -> APIRouter:
    """The API's routes; the `/act` body schema carries the configured batch limit."""
    router = APIRouter()
    handler = handler or ActHandler(settings)
    expected_key = settings.api_key.get_secret_value().encode() if settings.api_key else None

    async def require_api_key(
        request: Request,
        _key: str | None = Security(_api_key_header),
        _bearer_token: HTTPAuthorizationCredentials | None = Security(_bearer),
    ) -> None:
        """The API-key check as a dependency; its parameters document the two ways to send the key."""
        if expected_key is not None:
            _check_key(_headers(request.scope, (b"x-api-key", b"authorization")), expected_key)

    errors: dict[int | str, dict[str, Any]] = {
        code: {"model": ErrorResponse, "description": text}
        for code, text in (
            (400, "malformed HTTP framing, e.g. an invalid Content-Length"),
            (401, "missing or wrong API key (only when PUSHT_API_KEY is set)"),
            (404, "unknown policy; the message lists the loaded ones"),
            (413, "request body larger than PUSHT_MAX_BODY_BYTES"),
            (422, "invalid body: broken JSON, wrong shapes or types, non-finite or out-of-range values"),
            (503, "not ready yet, or the policy's queue is full (retry later)"),
        )
    }
    body_schema = handler.request_model.model_json_schema(ref_template="#/components/schemas/{model}")

    @router.post(
        "/act",
        response_model=ActResponse,
        responses=errors,
        summary="Action chunks for one state or a batch of states",
        openapi_extra={
            "requestBody": {"required": True, "content": {"application/json": {"schema": body_schema}}},
            # Documented like /policies' dependency, but checked inline to keep the hot path lean.
            "security": [{"APIKeyHeader": []}, {"HTTPBearer": []}],
        },
    )
    async def act(request: Request) -> Response:
        """Run a policy. Concurrent requests for one policy share model calls (dynamic batching)."""
        status, body, headers = await handler(request.app.state.service, request.scope, request.receive)
        return Response(body, status_code=status, media_type="application/json", headers=headers)

    @router.get("/policies", response_model=PoliciesResponse, responses={k: errors[k] for k in (401, 503)})
    async def policies(request: Request, _: None = Security(require_api_key)) -> PoliciesResponse:
        """The loaded policies with their parameter counts and evaluation results (from the cards)."""
        service: ServiceState = request.app.state.service
        if not service.ready:
            raise ServiceError(503, "policies are still loading", {"Retry-After": "1"})
        infos = []
        for name, policy in sorted(service.policies.items()):
            card = policy.card
            infos.append(
                PolicyInfo(
                    name=name,
                    kind=policy.kind,
                    num_parameters=card.get("num_parameters"),
                    num_steps=policy.default_num_steps if policy.kind == "flow" else None,
                    steps=card.get("steps"),
                    evaluation=card.get("evaluation"),
                    heldout_evaluation=card.get("heldout_evaluation"),
                    git_commit=card.get("git_commit"),
                )
            )
        return PoliciesResponse(backend=service.settings.backend, policies=infos)

    @router.get("/healthz", summary="Liveness: the process answers")
    async def healthz() -> dict[str, str]:
        """Always 200 while the server runs."""
        return {"status": "alive"}

    @router.get("/readyz", summary="Readiness: every policy is loaded", responses={503: errors[503]})
    async def readyz(request: Request) -> Response:
        """200 once every policy is loaded, 503 before (and while shutting down)."""
        service: ServiceState | None = getattr(request.app.state, "service", None)
        if service is None or not service.ready:
            return json_error(503, "not ready: policies are still loading", {"Retry-After": "1"})
        return Response(json.dumps({"status": "ready", "policies": sorted(service.policies)}), media_type="application/json")

    @router.get("/metrics", include_in_schema=False)
    async def metrics(request: Request) -> Response:
        """Prometheus metrics."""
        service: ServiceState = request.app.state.service
        return Response(service.metrics.render(), media_type=CONTENT_TYPE_LATEST)

    return router


class ActHandler:
    """`POST /act` as a plain function of (service state, ASGI scope, receive) -> (status, JSON bytes, headers)."""

    def __init__(self, settings: Settings) -> None:
        self.request_model = act_request_model(settings.max_states)
        self.max_body = settings.max_body_bytes
        self.expected_key = settings.api_key.get_secret_value().encode() if settings.api_key else None

    async def __call__(self, service: ServiceState, scope: Scope, receive: Receive) -> tuple[int, bytes, dict[str, str] | None]:
        """Answer one request; every problem becomes a JSON error with a 4xx/503 status."""
        try:
            return 200, await self._act(service, scope, receive), None
        except ServiceError as exc:
            return exc.status, json.dumps({"detail": exc.detail}).encode(), exc.headers

    async def _act(self, service: ServiceState, scope: Scope, receive: Receive) -> bytes:
        headers = _headers(scope, (b"content-length", b"x-api-key", b"authorization"))
        if self.expected_key is not None:
            _check_key(headers, self.expected_key)
        if not service.ready:
            raise ServiceError(503, "policies are still loading", {"Retry-After": "1"})
        body = await _read_body(receive, headers.get(b"content-length"), self.max_body)
        try:
            req = self.request_model.model_validate_json(body)
        except ValidationError as exc:
            raise ServiceError(422, exc.errors(include_url=False, include_input=False, include_context=False)) from None
        batcher = service.batchers.get(req.policy)
        if batcher is None:
            raise ServiceError(404, f"unknown policy {req.policy!r}; loaded policies: {sorted(service.batchers)}")
        policy = batcher.policy
        num_steps = req.num_steps
        if policy.kind != "flow":
            num_steps = None  # mse has no integration steps, just as it has no noise
        elif num_steps is not None:
            problem = policy.check_num_steps(num_steps)
            if problem is not None:
                raise ServiceError(422, [{"loc": ["num_steps"], "msg": problem, "type": "value_error"}])
        single = req.state is not None
        states = np.array([req.state] if single else req.states, dtype=np.float32)
        try:
            actions = await batcher.submit(states, req.seed, num_steps)
        except Overloaded as exc:
            raise ServiceError(503, str(exc), {"Retry-After": "1"}) from None
        except Exception as exc:  # a backend failure is our bug, but the client still gets JSON
            log.exception("policy %r failed on %d states", policy.name, len(states))
            raise ServiceError(500, f"policy {policy.name!r} failed: {type(exc).__name__}: {exc}") from None
        if not np.isfinite(actions).all():
            raise ServiceError(500, f"policy {policy.name!r} produced non-finite actions")
        payload = {
            "policy": policy.name,
            "kind": policy.kind,
            "backend": policy.backend,
            "actions": np.ascontiguousarray(actions[0] if single else actions),
        }
        # orjson writes float32 arrays directly (shortest float32 repr): ~1 us instead of ~25 us for json.
        return orjson.dumps(payload, option=orjson.OPT_SERIALIZE_NUMPY)


class ActFastPath:
    """ASGI middleware answering `POST /act` straight from the ASGI messages, skipping FastAPI's routing.

    Routing, dependency solving and response classes cost ~100+ us per request, about as much as a
    batched model call per state; everything else goes on to the FastAPI app.
    """

    def __init__(self, app: Callable, handler: ActHandler) -> None:
        self.app = app
        self.handler = handler

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["path"] != "/act" or scope["method"] != "POST":
            await self.app(scope, receive, send)
            return
        status, body, extra = await self.handler(scope["app"].state.service, scope, receive)
        headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
        if extra:
            headers.extend((k.lower().encode(), v.encode()) for k, v in extra.items())
        await send({"type": "http.response.start", "status": status, "headers": headers})
        await send({"type": "http.response.body", "body": body})


def _headers(scope: Scope, wanted: tuple[bytes, ...]) -> dict[bytes, str]:
    """The `wanted` request headers (lower-case names) as latin-1 strings."""
    return {name: value.decode("latin-1") for name, value in scope["headers"] if name in wanted}


def _check_key(headers: dict[bytes, str], expected: bytes) -> None:
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
