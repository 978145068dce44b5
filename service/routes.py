"""HTTP routes: `POST /act`, `GET /policies`, `/healthz`, `/readyz`, `/metrics`, `/docs` (offline).

`POST /act` is answered by `service.act.ActHandler` (usually through its fast-path middleware); its
route here documents it in the OpenAPI schema. `/docs` is Swagger UI with its JavaScript and CSS
served by the app itself (from the fastapi-offline package), so it works without internet access.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from fastapi import APIRouter, Request, Security
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse, Response
from fastapi.security import APIKeyHeader, HTTPAuthorizationCredentials, HTTPBearer

from service.act import ActHandler
from service.metrics import CONTENT_TYPE_LATEST
from service.request_input import ServiceError, check_key, json_error, request_headers
from service.schemas import ActResponse, ErrorResponse, PoliciesResponse, PolicyInfo
from service.settings import Settings
from service.state import ServiceState

__all__ = ["DOCS_ASSETS", "docs_assets_dir", "make_router"]

DOCS_ASSETS = "/docs-assets"
"""Where the app serves Swagger UI's own files."""

_api_key_header = APIKeyHeader(name="X-API-Key", auto_error=False, description="the PUSHT_API_KEY, when the service sets one")
_bearer = HTTPBearer(auto_error=False, description="the PUSHT_API_KEY as a bearer token, when the service sets one")


ERRORS: dict[int | str, dict[str, Any]] = {
    code: {"model": ErrorResponse, "description": text}
    for code, text in (
        (400, "malformed HTTP framing, e.g. an invalid Content-Length"),
        (401, "missing or wrong API key (only when PUSHT_API_KEY is set)"),
        (404, "unknown policy; the message lists the loaded ones"),
        (408, "the body took longer than PUSHT_BODY_TIMEOUT_S to arrive"),
        (413, "request body larger than PUSHT_MAX_BODY_BYTES"),
        (415, "the body is not sent as Content-Type: application/json"),
        (
            422,
            "invalid body: broken JSON, wrong shapes or types, non-finite or out-of-range values, "
            "seeds not one per state (at most 20 errors listed, then how many more)",
        ),
        (431, "request line and headers larger than PUSHT_MAX_HEADER_BYTES"),
        (503, "not ready yet, or the policy's queue is full (retry later)"),
    )
}


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
            check_key(request_headers(request.scope, (b"x-api-key", b"authorization")), expected_key)

    body_schema = handler.request_model.model_json_schema(ref_template="#/components/schemas/{model}")

    @router.post(
        "/act",
        response_model=ActResponse,
        responses=ERRORS,
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

    @router.get("/policies", response_model=PoliciesResponse, responses={k: ERRORS[k] for k in (401, 503)})
    async def policies(request: Request, _: None = Security(require_api_key)) -> PoliciesResponse:
        """The loaded policies with their chunk shapes, parameter counts and evaluation results (from the cards)."""
        service: ServiceState = request.app.state.service
        if not service.ready:
            raise ServiceError(503, "policies are still loading", {"Retry-After": "1"})
        infos = [_policy_info(name, policy, service) for name, policy in sorted(service.policies.items())]
        return PoliciesResponse(backend=service.settings.backend, policies=infos)

    _add_probe_routes(router)
    return router


def _add_probe_routes(router: APIRouter) -> None:
    """Liveness, readiness, metrics and the offline docs page: the routes that need no API key."""

    @router.get("/healthz", summary="Liveness: the process answers")
    async def healthz() -> dict[str, str]:
        """Always 200 while the server runs."""
        return {"status": "alive"}

    @router.get("/readyz", summary="Readiness: every policy is loaded", responses={503: ERRORS[503]})
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

    @router.get("/docs", include_in_schema=False)
    async def docs() -> HTMLResponse:
        """Swagger UI, its assets served by this app (no CDN)."""
        return get_swagger_ui_html(
            openapi_url="/openapi.json",
            title="Push-T policy service - docs",
            swagger_js_url=f"{DOCS_ASSETS}/swagger-ui-bundle.js",
            swagger_css_url=f"{DOCS_ASSETS}/swagger-ui.css",
            swagger_favicon_url=f"{DOCS_ASSETS}/favicon.png",
        )


def _policy_info(name: str, policy: Any, service: ServiceState) -> PolicyInfo:
    """What `/policies` says of one loaded policy, from its card and backend."""
    card = policy.card.data
    return PolicyInfo(
        name=name,
        kind=policy.card.computes,
        stochastic=policy.kind == "flow" and policy.uses_noise,
        default=name == service.default_policy,
        horizon=policy.horizon,
        action_dim=policy.action_dim,
        num_parameters=card.get("num_parameters"),
        num_steps=policy.default_num_steps if policy.kind == "flow" else None,
        network_evaluations=policy.network_evaluations(),
        steps=card.get("steps"),
        evaluation=card.get("evaluation"),
        heldout_evaluation=card.get("heldout_evaluation"),
        git_commit=card.get("git_commit"),
    )


def docs_assets_dir() -> Path:
    """The folder of Swagger UI's JavaScript, CSS and icon, installed with the serve extra (fastapi-offline)."""
    import fastapi_offline

    return Path(fastapi_offline.__file__).parent / "static"
