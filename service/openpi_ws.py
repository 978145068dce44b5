"""An openpi-compatible policy websocket at `ws://HOST:PORT/openpi/{policy}` (the protocol of openpi-client).

On connect the server sends its metadata (policy, kind, horizon, action and state dimensions); each
binary msgpack-numpy message `{"state": float32[5], "seed"?, "num_steps"?}` is answered with
`{"actions": float32[horizon, 2], "server_timing": {"infer_ms", "prev_total_ms"}}`, horizon the policy's
chunk length (its card's, in the metadata). Rows go through the
policy's Batcher, so concurrent connections share model calls with `/act`. A bad message gets a text
frame (openpi-client raises it as an error) and the connection stays open. With PUSHT_API_KEY set
the handshake needs `Authorization: Api-Key KEY` (as openpi sends it), `X-API-Key` or a bearer token.
"""

from __future__ import annotations

import json
import logging
import time
from typing import Any

import msgpack
import numpy as np
from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from fastapi.responses import Response

from service.batching import Batcher, Overloaded
from service.request_input import ServiceError, check_key, request_headers
from service.schemas import MAX_SEED
from service.settings import STATE_LIMIT, Settings
from service.state import ServiceState

__all__ = ["make_openpi_router", "pack", "unpack"]

log = logging.getLogger("uvicorn.error")

KEYS = ("state", "seed", "num_steps")
"""What a message may hold; `prev_state` is refused by name, since no shipped policy takes one."""


class BadMessage(ValueError):
    """A message the policy cannot act on; the text goes back to the client, and the connection stays."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


def _encode(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return {b"__ndarray__": True, b"data": obj.tobytes(), b"dtype": obj.dtype.str, b"shape": obj.shape}
    if isinstance(obj, np.generic):
        return {b"__npgeneric__": True, b"data": obj.item(), b"dtype": obj.dtype.str}
    return obj


def _decode(obj: dict) -> Any:
    # Numeric dtypes only: object arrays would need pickle, which openpi's format never uses either.
    if b"__ndarray__" in obj:
        dtype = np.dtype(obj[b"dtype"])
        if dtype.kind not in "fiu" or dtype.itemsize > 8:
            raise BadMessage(422, f"arrays must be numeric, got dtype {dtype.str!r}")
        return np.ndarray(buffer=obj[b"data"], dtype=dtype, shape=tuple(obj[b"shape"]))
    if b"__npgeneric__" in obj:
        dtype = np.dtype(obj[b"dtype"])
        if dtype.kind not in "fiu":
            raise BadMessage(422, f"scalars must be numeric, got dtype {dtype.str!r}")
        return dtype.type(obj[b"data"])
    return obj


def pack(obj: Any) -> bytes:
    """msgpack with numpy arrays as openpi-client encodes them."""
    return msgpack.packb(obj, default=_encode)


def unpack(data: bytes) -> Any:
    """The inverse of `pack`; BadMessage for anything that is not well-formed msgpack-numpy."""
    try:
        return msgpack.unpackb(data, object_hook=_decode, strict_map_key=False)
    except BadMessage:
        raise
    except Exception as exc:  # msgpack and numpy raise many types for malformed input
        raise BadMessage(400, f"the message is not valid msgpack-numpy: {type(exc).__name__}: {exc}") from None


def make_openpi_router(settings: Settings) -> APIRouter:
    """The `/openpi/{policy}` websocket route, and `/openpi` and `/` for the default policy."""
    router = APIRouter()
    expected = settings.api_key.get_secret_value().encode() if settings.api_key else None
    max_bytes = settings.max_body_bytes

    @router.websocket("/")  # openpi-client's WebsocketClientPolicy(host, port) connects here
    @router.websocket("/openpi")
    @router.websocket("/openpi/{policy}")
    async def openpi(websocket: WebSocket, policy: str | None = None) -> None:
        """Serve one openpi client: metadata first, then one action chunk per observation; no policy name: the default."""
        service: ServiceState = websocket.app.state.service
        policy = policy if policy is not None else service.default_policy
        try:
            batcher = _admit(websocket, service, policy, expected)
        except ServiceError as exc:
            await _deny(websocket, exc)
            return
        await websocket.accept()
        try:
            await _serve(websocket, batcher, max_bytes)
        except (WebSocketDisconnect, OSError):
            return  # the client left while its answer was pending: nothing to answer, nothing to log

    return router


async def _serve(websocket: WebSocket, batcher: Batcher, max_bytes: int) -> None:
    """Metadata first, then one answer per message until the client closes."""
    await websocket.send_bytes(pack(metadata(batcher)))
    prev_total_ms = None
    while True:
        message = await websocket.receive()
        if message["type"] == "websocket.disconnect":
            return
        start = time.monotonic()
        try:
            reply = await _act(batcher, message, max_bytes)
        except BadMessage as exc:
            await websocket.send_text(json.dumps({"status": exc.status, "error": str(exc)}))
            continue
        infer_ms = 1e3 * (time.monotonic() - start)
        reply["server_timing"] = (
            {"infer_ms": infer_ms} if prev_total_ms is None else {"infer_ms": infer_ms, "prev_total_ms": prev_total_ms}
        )
        await websocket.send_bytes(pack(reply))
        prev_total_ms = 1e3 * (time.monotonic() - start)


def metadata(batcher: Batcher) -> dict[str, Any]:
    """What the server sends on connect."""
    policy = batcher.policy
    return {
        "policy": policy.name,
        "kind": policy.kind,
        "backend": policy.backend,
        "state_dim": policy.state_dim,
        "horizon": policy.horizon,
        "action_dim": policy.action_dim,
        "num_steps": policy.default_num_steps if policy.kind == "flow" else None,
        "keys": list(KEYS),
    }


def _admit(websocket: WebSocket, service: ServiceState, policy: str, expected: bytes | None) -> Batcher:
    """The policy's batcher if the handshake may go on; else ServiceError (401, 403, 404, 503)."""
    headers = request_headers(websocket.scope, (b"x-api-key", b"authorization", b"origin"))
    if expected is not None:
        check_key(headers, expected)
    if b"origin" in headers:  # browsers always send Origin on websockets, which CORS does not protect
        raise ServiceError(403, "websockets from web pages (with an Origin header) are not served on /openpi")
    if not service.ready:
        raise ServiceError(503, "policies are still loading", {"Retry-After": "1"})
    batcher = service.batchers.get(policy)
    if batcher is None:
        raise ServiceError(404, f"unknown policy {policy!r}; loaded policies: {sorted(service.batchers)}")
    return batcher


async def _deny(websocket: WebSocket, exc: ServiceError) -> None:
    """Refuse the handshake with an HTTP JSON error where the server can send one, else close it (403)."""
    if "websocket.http.response" in websocket.scope.get("extensions", {}):
        body = json.dumps({"detail": exc.detail}).encode()
        await websocket.send_denial_response(
            Response(body, status_code=exc.status, media_type="application/json", headers=exc.headers)
        )
    else:
        await websocket.close(code=1008, reason=str(exc.detail)[:120])


async def _act(batcher: Batcher, message: dict[str, Any], max_bytes: int) -> dict[str, Any]:
    """`{"actions": float32[horizon, action_dim]}` for one message; BadMessage for a bad one."""
    data = message.get("bytes")
    if data is None:
        raise BadMessage(400, "send observations as binary msgpack-numpy frames (openpi-client's format), not text")
    if len(data) > max_bytes:
        raise BadMessage(413, f"message of {len(data)} bytes exceeds the limit of {max_bytes} bytes")
    obs = unpack(data)
    policy = batcher.policy
    if not isinstance(obs, dict):
        raise BadMessage(422, f"a message must be a map like {{'state': float32[{policy.state_dim}]}}, got {type(obs).__name__}")
    if "prev_state" in obs:
        raise BadMessage(422, f"policy {policy.name!r} takes no prev_state; send 'state' only")
    unknown = sorted(map(str, set(obs) - set(KEYS)))
    if unknown:
        raise BadMessage(422, f"unknown keys {unknown}; a message takes {list(KEYS)}")
    if "state" not in obs:
        raise BadMessage(422, f"the message has no 'state' (float32[{policy.state_dim}]: agent x, y, block x, y, angle)")
    try:
        state = np.asarray(obs["state"])
    except ValueError:  # ragged nested lists
        state = np.asarray(None)
    if state.shape != (policy.state_dim,) or state.dtype.kind not in "fiu":
        raise BadMessage(
            422,
            f"'state' must be {policy.state_dim} numbers (float32[{policy.state_dim}]), "
            f"got shape {list(state.shape)} of {state.dtype}",
        )
    state = state.astype(np.float32)
    if not (np.isfinite(state).all() and (np.abs(state) <= STATE_LIMIT).all()):
        raise BadMessage(422, f"'state' values must be finite and within +-{STATE_LIMIT:g}")
    seed = _integer(obs, "seed", 0, MAX_SEED)
    num_steps = _integer(obs, "num_steps", 1, 10**6)
    if policy.kind != "flow":
        if num_steps is not None:  # as on /act
            raise BadMessage(
                422, f"policy {policy.name!r} is an {policy.kind} policy: one network pass, no sampler steps; omit num_steps"
            )
        seed = None  # mse draws no noise, as on /act
    elif num_steps is not None and (problem := policy.check_num_steps(num_steps)) is not None:
        raise BadMessage(422, problem)
    try:
        actions = await batcher.enqueue(state[None], seed, num_steps)
    except Overloaded as exc:
        raise BadMessage(503, str(exc)) from None
    except Exception as exc:  # a backend failure is our bug, but the client still gets a message
        log.exception("policy %r failed on an openpi message", policy.name)
        raise BadMessage(500, f"policy {policy.name!r} failed: {type(exc).__name__}: {exc}") from None
    if not np.isfinite(actions).all():
        raise BadMessage(500, f"policy {policy.name!r} produced non-finite actions")
    return {"actions": np.ascontiguousarray(actions[0], dtype=np.float32)}


def _integer(obs: dict[str, Any], key: str, low: int, high: int) -> int | None:
    """obs[key] as a Python int in low..high, or None when absent."""
    value = obs.get(key)
    if value is None:
        return None
    if isinstance(value, np.ndarray) and value.shape == ():
        value = value[()]
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or not low <= int(value) <= high:
        raise BadMessage(422, f"'{key}' must be an integer in {low}..{high}, got {value!r:.40}")
    return int(value)
