"""The FastAPI app: `uvicorn service.app:app` serves every policy in PUSHT_MODELS_DIR.

Assembles the pieces: settings (service.settings), backends (service.backends), dynamic batching
(service.batching), routes (service.routes) and metrics (service.metrics). Policies are loaded once
in the lifespan; a missing or corrupt model file stops startup with a message naming the file.
"""

from __future__ import annotations

import asyncio
import logging
from contextlib import asynccontextmanager
from typing import AsyncIterator

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import Response

from service.backends import ModelLoadError, load_policies
from service.batching import Batcher
from service.metrics import Metrics, MetricsMiddleware
from service.routes import (
    ActFastPath,
    ActHandler,
    ServiceError,
    json_error,
    make_router,
)
from service.settings import Settings, get_settings
from service.state import ServiceState

__all__ = ["app", "create_app"]

# uvicorn configures this logger, so startup messages appear in its output.
log = logging.getLogger("uvicorn.error")

NEVER_SHED_CONNECTIONS = 32
ROUTES = frozenset({"/act", "/policies", "/healthz", "/readyz", "/metrics", "/docs", "/openapi.json"})


def create_app(settings: Settings | None = None) -> FastAPI:
    """Build the app for `settings` (default: from the environment); policies load in its lifespan."""
    settings = settings or get_settings()
    metrics = Metrics()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        service = ServiceState(settings=settings, metrics=metrics)
        app.state.service = service
        try:
            service.policies = await asyncio.to_thread(load_policies, settings)
        except ModelLoadError as exc:
            log.error("cannot start: %s", exc)
            raise
        for name, policy in service.policies.items():
            service.batchers[name] = Batcher(
                policy,
                max_rows=settings.batch_max_rows,
                max_wait_s=settings.batch_max_wait_ms / 1000.0,
                # 32 concurrent connections, each with a full request, must never be shed.
                queue_limit=max(settings.queue_limit, NEVER_SHED_CONNECTIONS * settings.max_states),
                observe=metrics.observe_batch,
            )
        if not settings.access_log:
            logging.getLogger("uvicorn.access").setLevel(logging.WARNING)
        service.ready = True
        log.info(
            "ready: %d policies (%s) on the %s backend from %s",
            len(service.policies), ", ".join(sorted(service.policies)), settings.backend, settings.models_dir,
        )
        try:
            yield
        finally:
            service.ready = False
            for batcher in service.batchers.values():
                await asyncio.to_thread(batcher.close)

    app = FastAPI(
        title="Push-T policy service",
        version="0.1.0",
        description=(
            "Action chunks from behavioral-cloning policies (MSE and flow matching) for Push-T. "
            "States and actions are in env units: pixels in 0..512, angle in radians."
        ),
        lifespan=lifespan,
    )
    app.state.service = ServiceState(settings=settings, metrics=metrics)
    handler = ActHandler(settings)
    app.include_router(make_router(settings, handler))
    _document_policy_names(app)

    @app.exception_handler(ServiceError)
    async def _service_error(request: Request, exc: ServiceError) -> Response:
        return json_error(exc.status, exc.detail, exc.headers)

    @app.exception_handler(RequestValidationError)
    async def _validation_error(request: Request, exc: RequestValidationError) -> Response:
        # FastAPI's default handler echoes the input, which may hold NaN (not JSON-serializable).
        detail = [{"loc": list(e.get("loc", ())), "msg": e.get("msg", ""), "type": e.get("type", "")} for e in exc.errors()]
        return json_error(422, detail)

    # Added last = outermost: metrics see every request, including those the fast path answers.
    app.add_middleware(ActFastPath, handler=handler)
    app.add_middleware(MetricsMiddleware, metrics=metrics, routes=ROUTES)
    return app


def _document_policy_names(app: FastAPI) -> None:
    """Once the policies are loaded, list their names as the `policy` enum of POST /act in the OpenAPI schema."""
    base_openapi = app.openapi

    def openapi() -> dict:
        schema = base_openapi()  # FastAPI builds it once and caches it on the app
        service: ServiceState = app.state.service
        if service.ready:
            body = schema["paths"]["/act"]["post"]["requestBody"]["content"]["application/json"]["schema"]
            body["properties"]["policy"]["enum"] = sorted(service.policies)
        return schema

    app.openapi = openapi  # type: ignore[method-assign]


app = create_app()
