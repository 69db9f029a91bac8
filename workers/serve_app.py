"""The Ray Serve application that labels single scans: `workers.serve_app:build_app`.

    serve deploy config.yaml      # import_path: workers.serve_app:build_app, args: {checkpoint: ...}

The application is one deployment, `ScanModel`, whose replicas each hold the network (one GPU per
replica where the cluster has or can add GPUs), gather concurrent requests into batches of up to
`batch_size` scans with `@serve.batch`, and answer in the exchange of `workers.scan_wire`. Its
arguments are the network options by name, as `rangeret serve` takes them (`checkpoint`,
`profile`, `model`, `height`, `width`, `fov_up`, `fov_down`, `batch_size`, `knn`, `device`,
`precision`, `backend`, `tta_flip`, `tta_shifts`; `knn: false` is `--no-knn`), and
`batch_wait_ms`, the longest a request waits for others to fill its batch. Autoscaling,
backpressure (`max_ongoing_requests`, `max_queued_requests`) and health checks have defaults here
that a Serve config's `deployments` entry overrides.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Mapping
from typing import Any

import numpy as np
from ray import serve
from starlette.requests import Request
from starlette.responses import JSONResponse, Response

from rangeret.commands import CommandError
from rangeret.inference.results import ScanOutcome
from rangeret.io.scans import ScanFormatError, parse_scan
from rangeret.options import NETWORK_OPTIONS, network_args, spec_from_values
from workers.cluster import read_resources
from workers.scan_wire import (
    INFO_PATH,
    OCTET,
    SCANS_PATH,
    encode_labels,
    query_flag,
)
from workers.scans import ScanWorker
from workers.sizing import ClusterResources, replica_gpus

log = logging.getLogger(__name__)

DEPLOYMENT = "ScanModel"
#: The longest a request waits for others to fill its batch unless `batch_wait_ms` says otherwise.
DEFAULT_BATCH_WAIT_MS = 10.0
#: Requests waiting for a replica beyond which Serve answers 503 (backpressure).
DEFAULT_MAX_QUEUED = 128
#: How often Serve calls a replica's health check, and how long it may take.
HEALTH_CHECK_PERIOD_S = 10.0
HEALTH_CHECK_TIMEOUT_S = 30.0

Item = tuple[np.ndarray, bool, bool]


class ScanModel:
    """One replica: the network, a batcher in front of it, and the HTTP exchange."""

    def __init__(self, values: Mapping[str, object], batch_wait_ms: float) -> None:
        import ray

        spec = spec_from_values(dict(values))
        cpus = ray.get_runtime_context().get_assigned_resources().get("CPU", 1.0)
        self.worker = ScanWorker(spec, cpus)
        self.record = self.worker.profile.points
        self.described = {**self.worker.info(), "batch_size": int(values.get("batch_size", 1))}
        self.label_one.set_max_batch_size(self.described["batch_size"])
        self.label_one.set_batch_wait_timeout_s(batch_wait_ms / 1000)
        self._failure: str | None = None

    @serve.batch(max_batch_size=1, batch_wait_timeout_s=DEFAULT_BATCH_WAIT_MS / 1000)
    async def label_one(self, items: list[Item]) -> list[ScanOutcome]:
        """A batch of requests labelled, one network pass per set of equal options."""
        return await asyncio.to_thread(self._label_items, items)

    def _label_items(self, items: list[Item]) -> list[ScanOutcome]:
        results: list[ScanOutcome | None] = [None] * len(items)
        for options in dict.fromkeys((knn, conf) for _, knn, conf in items):
            indices = [i for i, item in enumerate(items) if item[1:] == options]
            try:
                labelled = self.worker.predict([items[i][0] for i in indices], *options)
            except Exception as exc:
                self._failure = f"{type(exc).__name__}: {exc}"
                raise
            for i, result in zip(indices, labelled, strict=True):
                results[i] = result
        self._failure = None
        return results  # type: ignore[return-value]

    async def __call__(self, request: Request) -> Response:
        """`POST .../scans` labels the body's scan; `GET .../info` describes the network."""
        path = request.url.path.rstrip("/")
        if path.endswith(INFO_PATH) and request.method == "GET":
            return JSONResponse(self.described)
        if not (path.endswith(SCANS_PATH) and request.method == "POST"):
            return JSONResponse({"detail": f"No such operation: {request.method} {path}."}, 404)
        try:
            knn = query_flag(request.query_params.get("knn"), True, "knn")
            confidence = query_flag(request.query_params.get("confidence"), False, "confidence")
            points = parse_scan(await request.body(), "the scan", record=self.record)
        except ScanFormatError as exc:
            return JSONResponse({"detail": f"The scan is malformed: {exc.problem}."}, 400)
        except ValueError as exc:
            return JSONResponse({"detail": f"{str(exc).capitalize()}."}, 400)
        start = time.perf_counter()
        result = await self.label_one((points, knn, confidence))
        if isinstance(result, str):
            return JSONResponse({"detail": f"The scan cannot be projected: {result}."}, 422)
        body, headers = encode_labels(result)
        headers["Server-Timing"] = f"label;dur={(time.perf_counter() - start) * 1000:.1f}"
        return Response(body, media_type=OCTET, headers=headers)

    def check_health(self) -> None:
        """Serve's health check: a replica whose last network pass failed is replaced."""
        if self._failure is not None:
            raise RuntimeError(f"the last network pass failed: {self._failure}")


def deployment_options(batch_size: int, gpus: float) -> dict[str, Any]:
    """The deployment's defaults: backpressure sized to the batch (one batch running, one
    gathering), autoscaling on the requests in flight per replica, and health checks."""
    return {
        "name": DEPLOYMENT,
        "max_ongoing_requests": max(2, 2 * batch_size),
        "max_queued_requests": DEFAULT_MAX_QUEUED,
        "autoscaling_config": {
            "min_replicas": 1,
            "max_replicas": 4,
            "target_ongoing_requests": max(1, batch_size),
        },
        "ray_actor_options": {"num_cpus": 1, "num_gpus": gpus},
        "health_check_period_s": HEALTH_CHECK_PERIOD_S,
        "health_check_timeout_s": HEALTH_CHECK_TIMEOUT_S,
    }


def build_app(args: Mapping[str, object]) -> serve.Application:
    """The application for Serve config arguments: network options by name and `batch_wait_ms`;
    an unknown or bad argument is one sentence naming it, before any replica starts."""
    known = (*NETWORK_OPTIONS, "batch_wait_ms")
    unknown = sorted(set(args) - set(known))
    if unknown:
        raise ValueError(
            f"unknown argument(s) {', '.join(unknown)} of the rangeret Serve application; it "
            f"takes {', '.join(known)}"
        )
    values = {k: v for k, v in args.items() if k in NETWORK_OPTIONS}
    try:
        parsed = network_args(values)
    except CommandError as exc:
        raise ValueError(str(exc)) from exc
    wait = float(args.get("batch_wait_ms", DEFAULT_BATCH_WAIT_MS))  # type: ignore[arg-type]
    if wait < 0:
        raise ValueError(f"batch_wait_ms must not be negative, got {wait:g}")
    resources = read_resources() if parsed.device == "auto" else ClusterResources()
    options = deployment_options(parsed.batch_size, replica_gpus(parsed.device, resources))
    return serve.deployment(**options)(ScanModel).bind(values, wait)
