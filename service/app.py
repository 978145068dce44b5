"""The FastAPI app: `uvicorn service.app:app` serves every policy in PUSHT_MODELS_DIR.

Assembles the pieces: settings (service.settings), policies (service.backends, on `acting`), dynamic batching
(service.batching), the /act hot path (service.act), routes (service.routes), ASGI guards
(service.guard) and metrics (service.metrics). Policies are loaded once in the lifespan; a bad
setting, card or model file stops startup with one line naming the variable or the file.
`python -m service` (service.__main__) adds connection-level limits on top.
"""

from __future__ import annotations

import asyncio
import logging
from contextlib import asynccontextmanager
from functools import partial
from typing import AsyncIterator, Callable

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import Response
from fastapi.staticfiles import StaticFiles
from starlette.applications import Starlette

from service import protocol
from service.act import ActFastPath, ActHandler
from service.backends import ModelLoadError, default_policy, load_policies
from service.batching import Batcher
from service.guard import HeaderLimit, QuietStartupFailure, Refusal
from service.metrics import Metrics, MetricsMiddleware
from service.oip import make_oip_router
from service.openpi_ws import make_openpi_router
from service.request_input import ServiceError, cap_errors, json_error
from service.routes import DOCS_ASSETS, docs_assets_dir, make_router
from service.settings import Settings, SettingsError, get_settings
from service.state import ServiceState
from service.viewer import VIEWER_ASSETS, make_viewer_router, viewer_assets_dir

__all__ = ["app", "create_app"]

# uvicorn configures this logger, so startup messages appear in its output.
log = logging.getLogger("uvicorn.error")

NEVER_SHED_CONNECTIONS = 32
ROUTES = frozenset({"/act", "/policies", "/healthz", "/readyz", "/metrics", "/docs", "/openapi.json", "/viewer"})


def create_app(settings: Settings | None = None) -> FastAPI:
    """Build the app for `settings` (default: from the environment); policies load in its lifespan."""
    settings = settings or get_settings()
    metrics = Metrics()
    problems: list[str] = []

    lifespan = partial(_lifespan, settings, metrics, problems)
    app = _PolicyApp(
        title="Push-T policy service",
        version="0.1.0",
        description=(
            "Action chunks from behavioral-cloning policies (MSE and flow matching) for Push-T. "
            "States and actions are in env units: pixels in 0..512, angle in radians."
        ),
        lifespan=lifespan,
        docs_url=None,  # /docs is our own route, with Swagger UI's assets served locally
        redoc_url=None,
    )
    app.state.service = ServiceState(settings=settings, metrics=metrics)
    handler = ActHandler(settings)
    app.include_router(make_router(settings, handler))
    app.include_router(make_oip_router(settings))  # KServe Open Inference Protocol v2 under /v2 (service.oip)
    app.include_router(make_openpi_router(settings))  # openpi-compatible websocket /openpi/{policy} (service.openpi_ws)
    app.mount(DOCS_ASSETS, StaticFiles(directory=docs_assets_dir()), name="docs-assets")
    app.include_router(make_viewer_router(settings))  # GET /viewer and its websocket (service.viewer)
    app.mount(VIEWER_ASSETS, StaticFiles(directory=viewer_assets_dir()), name="viewer-assets")
    _document_policy_names(app)

    @app.exception_handler(ServiceError)
    async def _service_error(request: Request, exc: ServiceError) -> Response:
        return json_error(exc.status, exc.detail, exc.headers)

    @app.exception_handler(RequestValidationError)
    async def _validation_error(request: Request, exc: RequestValidationError) -> Response:
        # FastAPI's default handler echoes the input, which may hold NaN (not JSON-serializable).
        return json_error(422, cap_errors(exc.errors()))

    app.fast_path = lambda stack: ActFastPath(stack, handler, metrics, settings.max_header_bytes)
    # Added last = outermost: metrics see every request (the fast path records its own).
    app.add_middleware(HeaderLimit, max_bytes=settings.max_header_bytes)
    app.add_middleware(MetricsMiddleware, metrics=metrics, routes=ROUTES)
    app.add_middleware(QuietStartupFailure, problems=problems)
    app.own_middleware = list(app.user_middleware)
    return app


@asynccontextmanager
async def _lifespan(settings: Settings, metrics: Metrics, problems: list[str], app: FastAPI) -> AsyncIterator[None]:
    """Load the policies and start a batcher for each; ready until shutdown, then close the batchers."""
    service = ServiceState(settings=settings, metrics=metrics)
    app.state.service = service
    try:
        service.policies = await asyncio.to_thread(load_policies, settings)
        service.default_policy = default_policy(service.policies, settings.default_policy)
    except ModelLoadError as exc:
        problems.append(str(exc))  # QuietStartupFailure prints it as uvicorn's one error line
        raise
    for name, policy in service.policies.items():
        service.batchers[name] = Batcher(
            policy,
            max_rows=settings.batch_max_rows,
            max_cost=settings.batch_max_cost,
            max_wait_s=settings.batch_max_wait_ms / 1000.0,
            inline_max_cost=settings.inline_max_cost,
            # 32 concurrent connections, each with a full request, must never be shed.
            queue_limit=max(settings.queue_limit, NEVER_SHED_CONNECTIONS * settings.max_states * policy.network_evaluations()),
            observe=metrics.observe_batch,
        )
    _configure_logs(settings)
    service.ready = True
    log.info(
        "ready: %d policies (%s; default %s) on the %s backend from %s",
        len(service.policies),
        ", ".join(sorted(service.policies)),
        service.default_policy,
        settings.backend,
        settings.models_dir,
    )
    try:
        yield
    finally:
        service.ready = False
        for batcher in service.batchers.values():
            await asyncio.to_thread(batcher.close)


def _configure_logs(settings: Settings) -> None:
    if not protocol.ENTRY_POINT:
        log.warning(
            "started without `python -m service`: idle and slow connections, connection count, shutdown time and "
            "websocket frames (size, compression) are bounded only by the server's own flags, and requests that are not "
            "HTTP get text, not JSON (see docs/service.md)"
        )
    if not settings.access_log:
        access = logging.getLogger("uvicorn.access")
        access.setLevel(logging.WARNING)
        # As uvicorn's --no-access-log: a connection whose logger has no handler does not even build the line's
        # arguments (the level alone still has it format the client address and path of every request).
        access.handlers.clear()


class _PolicyApp(FastAPI):
    """FastAPI with `fast_path` wrapped around its own middleware stack: `POST /act` skips it (service.act.ActFastPath).

    Middleware added after `create_app` (`app.add_middleware`, e.g. service.ray_serve's replica header) wraps the
    whole app, the fast path included, as a user of FastAPI expects."""

    fast_path: Callable[[Callable], Callable] | None = None
    own_middleware: list = []
    _act_entry: Callable | None = None
    """The fast path itself, when no middleware was added around it: /act calls it directly."""

    async def __call__(self, scope, receive, send) -> None:
        # FastAPI's native telemetry looks its OpenTelemetry providers up on every request (~10 us, 4 % of /act's p50 with
        # the mse policy): POST /act goes straight to the middleware stack, where the fast path answers it (its request
        # metrics at /metrics); everything else gets FastAPI's full treatment.
        if self.fast_path is not None and scope["type"] == "http" and scope["path"] == "/act" and not self.root_path:
            entry = self._act_entry
            if entry is not None and self.middleware_stack is not None:
                scope["app"] = self  # as Starlette.__call__, one coroutine frame less
                await entry(scope, receive, send)
                return
            await Starlette.__call__(self, scope, receive, send)
            return
        await super().__call__(scope, receive, send)

    def build_middleware_stack(self) -> Callable:
        added, own = self.user_middleware, self.own_middleware
        self.user_middleware = [m for m in added if any(m is o for o in own)]
        try:
            app = super().build_middleware_stack()
        finally:
            self.user_middleware = added
        self._act_entry = None
        if self.fast_path is not None:
            app = self.fast_path(app)
            self._act_entry = app
        for cls, args, kwargs in reversed([m for m in added if not any(m is o for o in own)]):
            app = cls(app, *args, **kwargs)
            self._act_entry = None
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


def _app_from_environment() -> FastAPI | Refusal:
    """The app for the environment's settings; a bad PUSHT_ variable leaves an app whose startup names it."""
    try:
        return create_app(get_settings())
    except SettingsError as exc:
        return Refusal(str(exc))


app = _app_from_environment()
