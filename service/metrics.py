"""Prometheus metrics: requests by route and status, request latency, and model-call batch sizes.

Each app gets its own registry, so several apps can live in one process (tests) without clashing.
`MetricsMiddleware` is plain ASGI: it costs a few microseconds per request, unlike BaseHTTPMiddleware.
Observations are appended to a buffer and folded into the Prometheus metrics in bulk (at every render,
and every FOLD_EVERY observations): a model call evicts the CPU caches, and prometheus_client's locked
observe calls, run cold once per request, cost ~25 us of a /act request's path; an append costs ~2.
"""

from __future__ import annotations

import time
from collections import deque
from typing import Any, Awaitable, Callable

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Histogram,
    generate_latest,
)

__all__ = ["Metrics", "MetricsMiddleware", "CONTENT_TYPE_LATEST"]

_LATENCY_BUCKETS = (0.0005, 0.001, 0.002, 0.003, 0.005, 0.0075, 0.01, 0.02, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0)
_ROW_BUCKETS = (1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024, 2048, 4096)

FOLD_EVERY = 256
"""Buffered observations are folded into the metrics once this many wait (~0.5 ms, every 256 requests)."""


class Metrics:
    """The service's metrics in their own registry."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.requests = Counter(
            "pusht_http_requests",
            "HTTP requests by route, method and status",
            ["route", "method", "status"],
            registry=self.registry,
        )
        self.latency = Histogram(
            "pusht_http_request_duration_seconds",
            "time from request start to the last response byte",
            ["route"],
            buckets=_LATENCY_BUCKETS,
            registry=self.registry,
        )
        self.batch_rows = Histogram(
            "pusht_batch_rows", "state rows per model call", ["policy"], buckets=_ROW_BUCKETS, registry=self.registry
        )
        self.batch_requests = Histogram(
            "pusht_batch_requests",
            "requests merged into one model call",
            ["policy"],
            buckets=_ROW_BUCKETS,
            registry=self.registry,
        )
        self._request_children: dict[tuple[str, str, int], tuple[Any, Any]] = {}
        self._batch_children: dict[str, tuple[Any, Any]] = {}
        # deque appends and pops are atomic: the worker threads' observe_batch needs no lock.
        self._requests_seen: deque[tuple[str, str, int, float]] = deque()
        self._batches_seen: deque[tuple[str, int, int]] = deque()

    def observe_request(self, route: str, method: str, status: int, seconds: float) -> None:
        """Count one HTTP request and record its latency."""
        seen = self._requests_seen
        seen.append((route, method, status, seconds))
        if len(seen) >= FOLD_EVERY:
            self.fold()

    def observe_batch(self, policy: str, rows: int, requests: int) -> None:
        """Record one model call of `rows` state rows merged from `requests` requests."""
        seen = self._batches_seen
        seen.append((policy, rows, requests))
        if len(seen) >= FOLD_EVERY:
            self.fold()

    def fold(self) -> None:
        """Move the buffered observations into the Prometheus metrics."""
        take = self._requests_seen.popleft
        children_of = self._request_children
        while True:
            try:
                route, method, status, seconds = take()
            except IndexError:
                break
            key = (route, method, status)
            children = children_of.get(key)
            if children is None:
                children = children_of[key] = (self.requests.labels(route, method, str(status)), self.latency.labels(route))
            children[0].inc()
            children[1].observe(seconds)
        take_batch = self._batches_seen.popleft
        while True:
            try:
                policy, rows, requests = take_batch()
            except IndexError:
                break
            children = self._batch_children.get(policy)
            if children is None:
                children = self._batch_children[policy] = (self.batch_rows.labels(policy), self.batch_requests.labels(policy))
            children[0].observe(rows)
            children[1].observe(requests)

    def render(self) -> bytes:
        """The Prometheus text exposition of every metric."""
        self.fold()
        return generate_latest(self.registry)


Scope = dict[str, Any]
Receive = Callable[[], Awaitable[dict[str, Any]]]
Send = Callable[[dict[str, Any]], Awaitable[None]]


class MetricsMiddleware:
    """Counts HTTP requests and times them; unknown paths share one `other` label to bound cardinality."""

    def __init__(self, app: Callable, metrics: Metrics, routes: frozenset[str]) -> None:
        self.app = app
        self.metrics = metrics
        self.routes = routes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        path = scope["path"]
        route = path if path in self.routes else "other"
        status = 500

        async def send_wrapper(message: dict[str, Any]) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            self.metrics.observe_request(route, scope["method"], status, time.perf_counter() - start)
