"""KServe Open Inference Protocol v2 (what Triton and KServe speak) on the same app as `POST /act`.

`GET /v2`, `/v2/health/live`, `/v2/health/ready`, `/v2/models/{name}` and `/v2/models/{name}/ready`,
`POST /v2/models/{name}/infer` (each also under `/versions/1`): input `state` FP32 [B, 5] and, for
flow, `noise` FP32 [B, H, 2] or `seeds` INT64 [B] (one per row, as `/act`'s `seeds`) or a `seed`
request parameter; output `actions` FP32 [B, H, 2], H the policy's chunk length (its card's horizon,
in its model metadata). Tensors come as JSON `data` or binary (the
`Inference-Header-Content-Length` extension, tritonclient's default). Rows go through the policy's
Batcher, sharing model calls, key, body and queue limits with `/act`; errors are 4xx JSON with
`error` (what OIP clients read) and `detail` (as the rest of the API).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import orjson
from fastapi import APIRouter, Request
from fastapi.responses import Response
from pydantic import BaseModel, ValidationError

from acting import Policy
from service.act import await_actions
from service.batching import Batcher, Overloaded
from service.oip_tensors import VERSION, InferRequest, answer, input_tensors, invalid, model_metadata, split_body
from service.request_input import ServiceError, cap_errors, check_key, read_body, request_headers
from service.schemas import MAX_SEED
from service.settings import Settings
from service.state import ServiceState

__all__ = ["make_oip_router"]


# What a web page may send cross-site without a CORS preflight: refused, so a page cannot drive a policy.
SIMPLE_TYPES = ("text/plain", "application/x-www-form-urlencoded", "multipart/form-data")
WANTED_HEADERS = (
    b"content-length",
    b"content-type",
    b"content-encoding",
    b"origin",
    b"x-api-key",
    b"authorization",
    b"inference-header-content-length",
)


class OipErrorResponse(BaseModel):
    """Every OIP error: `error` is one message (what OIP clients show), `detail` as in the rest of the API."""

    error: str
    detail: str | list[dict[str, Any]]


ERRORS: dict[int | str, dict[str, Any]] = {
    code: {"model": OipErrorResponse, "description": text}
    for code, text in (
        (400, "malformed framing: Content-Length, Inference-Header-Content-Length, unclaimed binary data"),
        (401, "missing or wrong API key (only when PUSHT_API_KEY is set)"),
        (403, "a request from a web page (Origin header)"),
        (404, "unknown model or version; the message lists the loaded ones"),
        (408, "the body took longer than PUSHT_BODY_TIMEOUT_S to arrive"),
        (413, "request body larger than PUSHT_MAX_BODY_BYTES"),
        (415, "a form or text content type, or a compressed body"),
        (422, "invalid request: JSON, inputs (names, datatypes, shapes, values), parameters or outputs"),
        (503, "not ready yet, or the policy's queue is full (retry later)"),
    )
}


def oip_error(status: int, detail: Any, headers: dict[str, str] | None = None) -> Response:
    """A 4xx/5xx answer: `error` as one string for OIP clients, `detail` as in the rest of the API."""
    if isinstance(detail, str):
        message = detail
    else:
        message = "; ".join(f"{'.'.join(map(str, e['loc'])) or 'request'}: {e['msg']}" for e in detail)
    return Response(
        orjson.dumps({"error": message, "detail": detail}), status_code=status, media_type="application/json", headers=headers
    )


DEFAULT_ALIAS = "default"


def make_oip_router(settings: Settings) -> APIRouter:
    """The OIP v2 routes under /v2."""
    router = APIRouter(prefix="/v2", tags=["KServe Open Inference Protocol v2"])
    infer = OipInfer(settings)

    _add_probe_routes(router)

    @router.get("/models/{name}", summary="OIP model metadata", responses={k: ERRORS[k] for k in (404, 503)})
    @router.get("/models/{name}/versions/{version}", include_in_schema=False)
    async def metadata(request: Request, name: str, version: str | None = None) -> Response:
        """A policy's inputs and outputs."""
        try:
            _, batcher = _lookup(request, name, version)
        except ServiceError as exc:
            return oip_error(exc.status, exc.detail, exc.headers)
        return Response(orjson.dumps(model_metadata(name, batcher.policy)), media_type="application/json")

    @router.get("/models/{name}/ready", summary="OIP model readiness", responses={k: ERRORS[k] for k in (404, 503)})
    @router.get("/models/{name}/versions/{version}/ready", include_in_schema=False)
    async def model_ready(request: Request, name: str, version: str | None = None) -> Response:
        """200 when the policy is loaded, 404 for an unknown one, 503 while loading."""
        try:
            _lookup(request, name, version)
        except ServiceError as exc:
            return oip_error(exc.status, exc.detail, exc.headers)
        return Response(orjson.dumps({"name": name, "ready": True}), media_type="application/json")

    @router.post(
        "/models/{name}/infer",
        summary="OIP inference: actions FP32 [B, horizon, 2] for state FP32 [B, 5]",
        responses={200: {"content": {"application/json": {}, "application/octet-stream": {}}}, **ERRORS},
    )
    @router.post("/models/{name}/versions/{version}/infer", include_in_schema=False)
    async def infer_route(request: Request, name: str, version: str | None = None) -> Response:
        """Run a policy through its batcher, with /act's key, limits and error rules."""
        try:
            infer.check_request(request_headers(request.scope, WANTED_HEADERS))
            _, batcher = _lookup(request, name, version)
            return await infer(request, batcher, name)
        except ServiceError as exc:
            return oip_error(exc.status, exc.detail, exc.headers)

    return router


def _lookup(request: Request, name: str, version: str | None) -> tuple[ServiceState, Batcher]:
    """The service and the batcher of model `name` (or the default policy's, as `default`); ServiceError otherwise."""
    service: ServiceState = request.app.state.service
    if not service.ready:
        raise ServiceError(503, "policies are still loading", {"Retry-After": "1"})
    # `default` names the default policy (GET /policies), unless a policy has that name
    batcher = service.batchers.get(name) or (service.batchers.get(service.default_policy) if name == DEFAULT_ALIAS else None)
    if batcher is None:
        raise ServiceError(404, f"unknown model {name!r}; loaded models: {sorted(service.batchers)} (or {DEFAULT_ALIAS!r})")
    if version is not None and version != VERSION:
        raise ServiceError(404, f"model {name!r} has version {VERSION!r} only, not {version!r}")
    return service, batcher


def _add_probe_routes(router: APIRouter) -> None:
    """Server metadata, liveness and readiness."""

    @router.get("", summary="OIP server metadata")
    async def server_metadata() -> Response:
        """Name, version and the protocol extensions served (binary tensor data)."""
        return Response(
            orjson.dumps({"name": "pusht-service", "version": "0.1.0", "extensions": ["binary_tensor_data"]}),
            media_type="application/json",
        )

    @router.get("/health/live", summary="OIP liveness")
    async def live() -> Response:
        """Always 200 while the server runs."""
        return Response(b'{"live":true}', media_type="application/json")

    @router.get("/health/ready", summary="OIP readiness: every model is loaded", responses={503: ERRORS[503]})
    async def ready(request: Request) -> Response:
        """200 once every policy is loaded, 503 before and while shutting down."""
        service: ServiceState | None = getattr(request.app.state, "service", None)
        if service is None or not service.ready:
            return oip_error(503, "not ready: policies are still loading", {"Retry-After": "1"})
        return Response(b'{"ready":true}', media_type="application/json")


class OipInfer:
    """`POST /v2/models/{name}/infer`: read, validate, batch, answer in JSON or binary."""

    def __init__(self, settings: Settings) -> None:
        self.max_states = settings.max_states
        self.max_body = settings.max_body_bytes
        self.body_timeout = settings.body_timeout_s
        self.expected_key = settings.api_key.get_secret_value().encode() if settings.api_key else None

    def check_request(self, headers: dict[bytes, str]) -> None:
        """Key (401), browser origin (403), content type (415) and encoding (415) before anything is read."""
        if self.expected_key is not None:
            check_key(headers, self.expected_key)
        if b"origin" in headers:  # tritonclient sends no Content-Type, so a browser's no-type POST is told apart by Origin
            raise ServiceError(403, "requests from web pages (with an Origin header) are not served on /v2")
        media_type = headers.get(b"content-type", "").partition(";")[0].strip().lower()
        if media_type in SIMPLE_TYPES:
            raise ServiceError(
                415, f"send the body as application/json, application/octet-stream or without a type, not {media_type!r}"
            )
        if headers.get(b"content-encoding", "identity").strip().lower() != "identity":
            raise ServiceError(415, "compressed request bodies are not supported: send it uncompressed")

    async def __call__(self, request: Request, batcher: Batcher, name: str) -> Response:
        """Answer one inference request (the request has passed check_request and the model exists)."""
        headers = request_headers(request.scope, WANTED_HEADERS)
        body = await read_body(request.receive, headers.get(b"content-length"), self.max_body, self.body_timeout)
        head, tail = split_body(body, headers.get(b"inference-header-content-length"))
        try:
            req = InferRequest.model_validate_json(head)
        except ValidationError as exc:
            raise ServiceError(
                422, cap_errors(exc.errors(include_url=False, include_input=False, include_context=False))
            ) from None
        policy = batcher.policy
        seed, num_steps, binary_out = self._parameters(req, policy)
        tensors = input_tensors(req, tail, policy, self.max_states)
        states, noise, seeds = tensors["state"], tensors.get("noise"), tensors.get("seeds")
        if sum(x is not None for x in (noise, seeds, seed)) > 1:
            raise invalid(["inputs"], "give at most one of the `noise` input, the `seeds` input or the `seed` parameter")
        try:
            future = batcher.enqueue(states, seed, num_steps, None if seeds is None else seeds.tolist(), noise=noise)
        except Overloaded as exc:
            raise ServiceError(503, str(exc), {"Retry-After": "1"}) from None
        actions = await await_actions(future, batcher, request.receive, len(states))
        return answer(name, req.id, np.ascontiguousarray(actions, dtype=np.float32), binary_out)

    def _parameters(self, req: InferRequest, policy: Policy) -> tuple[int | None, int | None, bool]:
        """(seed, num_steps, binary output) from the request and output parameters."""
        params = dict(req.parameters)
        seed, num_steps = params.pop("seed", None), params.pop("num_steps", None)
        binary = params.pop("binary_data_output", False)
        if params:
            raise invalid(
                ["parameters"], f"unknown parameters {sorted(params)}; this server takes seed, num_steps, binary_data_output"
            )
        if seed is not None and (type(seed) is not int or not 0 <= seed <= MAX_SEED):
            raise invalid(["parameters", "seed"], f"seed must be an integer in 0..{MAX_SEED}")
        if type(binary) is not bool:
            raise invalid(["parameters", "binary_data_output"], "must be true or false")
        if num_steps is not None:
            if type(num_steps) is not int:
                raise invalid(["parameters", "num_steps"], "must be an integer")
            if policy.kind != "flow":  # as on /act
                raise invalid(
                    ["parameters", "num_steps"],
                    f"policy {policy.name!r} is an {policy.kind} policy: one network pass, no sampler steps; omit num_steps",
                )
            problem = policy.check_num_steps(num_steps)
            if problem is not None:
                raise invalid(["parameters", "num_steps"], problem)
        if policy.kind != "flow":
            seed = None  # mse draws no noise, as on /act
        for k, out in enumerate(req.outputs or []):
            if (
                out.name != "actions"
                or set(out.parameters) - {"binary_data"}
                or type(out.parameters.get("binary_data", binary)) is not bool
            ):
                raise invalid(["outputs", k], "the one output is `actions`, with the one parameter binary_data (true or false)")
            binary = out.parameters.get("binary_data", binary)
        return seed, num_steps, binary
