"""Prometheus metrics of the gateway: what it serves, requests, latency, scans labelled, batches
and queue depth.

Each app has its own registry, so several gateways (tests) in one process do not collide. The
request middleware labels by route template (`/v1/jobs/{job_id}`), never by raw path, so the
number of series stays bounded.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, Info, generate_latest
from prometheus_client.exposition import CONTENT_TYPE_LATEST
from starlette.requests import ClientDisconnect
from starlette.types import ASGIApp, Message, Receive, Scope, Send

log = logging.getLogger(__name__)

LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0)


class GatewayMetrics:
    """The gateway's counters, histograms and gauges in a registry of their own."""

    content_type = CONTENT_TYPE_LATEST

    def __init__(self, profile: str, models: dict[str, str] | None = None) -> None:
        self.registry = CollectorRegistry()
        self.info = Info(
            "rangeret_gateway",
            "What the gateway serves: the dataset profile of its default model",
            registry=self.registry,
        )
        self.info.info({"profile": profile})
        self.models = Gauge(
            "rangeret_model",
            "The models the gateway serves, with each one's profile (always 1)",
            ["model", "profile"],
            registry=self.registry,
        )
        for name, model_profile in (models or {}).items():
            self.models.labels(model=name, profile=model_profile).set(1)
        self.loaded = Gauge(
            "rangeret_model_loaded",
            "Whether each model's network is loaded in the gateway's process now (1) or not (0)",
            ["model"],
            registry=self.registry,
        )
        self.requests = Counter(
            "rangeret_http_requests",
            "HTTP requests answered, by method, route and status code",
            ["method", "route", "status"],
            registry=self.registry,
        )
        self.latency = Histogram(
            "rangeret_http_request_duration_seconds",
            "Time to answer an HTTP request, by method and route",
            ["method", "route"],
            buckets=LATENCY_BUCKETS,
            registry=self.registry,
        )
        self.scans = Counter(
            "rangeret_scans_labelled",
            "Scans labelled, by source (single-scan requests or jobs) and model",
            ["source", "model"],
            registry=self.registry,
        )
        self.points = Counter(
            "rangeret_points_labelled",
            "Points labelled by single-scan requests, by model",
            ["model"],
            registry=self.registry,
        )
        self.refused = Counter(
            "rangeret_scans_refused",
            "Single-scan requests refused with 503 because the gateway held as many as it may",
            registry=self.registry,
        )
        self.batch_size = Histogram(
            "rangeret_batch_scans",
            "Scans per network batch of single-scan requests",
            buckets=(1, 2, 4, 8, 16, 32, 64),
            registry=self.registry,
        )
        self.batch_latency = Histogram(
            "rangeret_batch_duration_seconds",
            "Time the workers took for one batch",
            buckets=LATENCY_BUCKETS,
            registry=self.registry,
        )
        self.queue_depth = Gauge(
            "rangeret_queue_depth",
            "Single-scan requests waiting for or in the workers",
            registry=self.registry,
        )
        self.jobs = Gauge(
            "rangeret_jobs",
            "Jobs known to the gateway, by state",
            ["state"],
            registry=self.registry,
        )

    def observe_batch(self, size: int, seconds: float) -> None:
        """Record one batch sent to the workers."""
        self.batch_size.observe(size)
        self.batch_latency.observe(seconds)

    def job_scans(self, count: int, model: str) -> None:
        """Record scans written by a job of `model`."""
        self.scans.labels(source="job", model=model).inc(count)

    def render(
        self,
        queue_depth: int,
        job_counts: dict[str, int],
        loaded: dict[str, bool] | None = None,
    ) -> bytes:
        """The Prometheus text exposition, with the gauges read now (`loaded`: whether each
        model's network is loaded, where the gateway keeps a pool)."""
        self.queue_depth.set(queue_depth)
        for name, is_loaded in (loaded or {}).items():
            self.loaded.labels(model=name).set(int(is_loaded))
        for state, count in job_counts.items():
            self.jobs.labels(state=state).set(count)
        return generate_latest(self.registry)


#: The `status` label of a request whose client went away before its body was read.
CLIENT_DISCONNECT = "client_disconnect"


class MetricsMiddleware:
    """ASGI middleware counting every HTTP request and timing it, by route template.

    A client that disconnects before its body is read is no server error: it is counted under
    the status `client_disconnect` and logged as one line, and nothing is answered.
    """

    def __init__(self, app: ASGIApp, metrics: Callable[[], GatewayMetrics | None]) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status: list[int | str] = [500]

        async def send_wrapper(message: Message) -> None:
            if message["type"] == "http.response.start":
                status[0] = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        except ClientDisconnect:
            status[0] = CLIENT_DISCONNECT
            log.info(
                "%s %s: the client disconnected before its request was read",
                scope.get("method", ""),
                scope.get("path", "")[:200],
            )
        finally:
            metrics = self.metrics()
            if metrics is not None:
                route = scope.get("route")
                path = getattr(route, "path", None) or "unmatched"
                method = scope.get("method", "")
                metrics.requests.labels(method=method, route=path, status=str(status[0])).inc()
                metrics.latency.labels(method=method, route=path).observe(
                    time.perf_counter() - start
                )
