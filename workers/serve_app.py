"""The Ray Serve application that labels single scans: `workers.serve_app:build_app`.

    serve deploy config.yaml      # import_path: workers.serve_app:build_app, args: {checkpoint: ...}

The application is one deployment, `ScanModel`, whose replicas each hold the network (one GPU per
replica where the cluster has or can add GPUs), gather concurrent requests into batches of up to
`batch_size` scans with `@serve.batch`, and answer in the exchange of `workers.scan_wire` through
a FastAPI app (`@serve.ingress`). Its arguments are the fields of
`rangeret.inference.spec.InferenceSpec` by name, as `rangeret serve` takes them as options
(`checkpoint`, `profile`, `model`, `height`, `width`, `fov_up`, `fov_down`, `batch_size`, `knn`,
`device`, `precision`, `backend`, `tta_flip`, `tta_shifts`; `knn: false` is `--no-knn`), and
`batch_wait_ms`, the longest a request waits for others to fill its batch. `batch_size` and
`batch_wait_ms` reach the replicas as the deployment's `user_config`, so a Serve config that
changes them there reconfigures running replicas without reloading the network. Autoscaling,
backpressure (`max_ongoing_requests`, `max_queued_requests`) and health checks have defaults here
that a Serve config's `deployments` entry overrides.
"""

import asyncio
import logging
import time
from collections.abc import Mapping
from typing import Any

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse, Response
from ray import serve

from rangeret.inference.predictor import Predictor
from rangeret.inference.results import ScanOutcome
from rangeret.inference.scan_worker import ScanRequest, ScanWorker, use_cpus
from rangeret.inference.spec import InferenceSpec, InferenceSpecError
from rangeret.io.scans import ScanFormatError, parse_scan
from workers.cluster import read_resources
from workers.scan_wire import INFO_PATH, OCTET, SCANS_PATH, encode_labels, query_flag
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
#: The application's own arguments besides the spec's fields.
APP_ARGUMENTS = ("batch_wait_ms",)

api = FastAPI(title="rangeret Serve application", openapi_url=None, docs_url=None)


@api.exception_handler(404)
async def _no_such_operation(request: Request, exc: Exception) -> JSONResponse:
    return JSONResponse({"detail": f"No such operation: {request.method} {request.url.path}."}, 404)


@serve.ingress(api)
class ScanModel:
    """One replica: the network, a batcher in front of it, and the HTTP exchange."""

    def __init__(self, spec: Mapping[str, Any]) -> None:
        import ray

        parsed = InferenceSpec.from_mapping(spec)
        use_cpus(ray.get_runtime_context().get_assigned_resources().get("CPU", 1.0))
        self.worker = ScanWorker(Predictor.from_spec(parsed))
        self.record = self.worker.profile.points
        self.described = {**self.worker.info(), "batch_size": parsed.batch_size}
        self._failure: str | None = None

    def reconfigure(self, config: Mapping[str, Any]) -> None:
        """Serve's `user_config`: the batch size and wait, changed in place on running replicas."""
        size = int(config.get("batch_size", 1))
        self.label_one.set_max_batch_size(size)
        self.label_one.set_batch_wait_timeout_s(
            float(config.get("batch_wait_ms", DEFAULT_BATCH_WAIT_MS)) / 1000
        )
        self.described["batch_size"] = size

    @serve.batch(max_batch_size=1, batch_wait_timeout_s=DEFAULT_BATCH_WAIT_MS / 1000)
    async def label_one(self, requests: list[ScanRequest]) -> list[ScanOutcome]:
        """A batch of requests labelled, one network pass per set of equal options."""
        return await asyncio.to_thread(self._label, requests)

    def _label(self, requests: list[ScanRequest]) -> list[ScanOutcome]:
        try:
            labelled = self.worker.label(requests)
        except Exception as exc:
            self._failure = f"{type(exc).__name__}: {exc}"
            raise
        self._failure = None
        return labelled

    @api.get(INFO_PATH)
    def info(self) -> dict:
        """The network this replica serves."""
        return self.described

    @api.post(SCANS_PATH)
    async def scans(self, request: Request) -> Response:
        """The body's scan labelled, in the exchange of `workers.scan_wire`."""
        try:
            knn = query_flag(request.query_params.get("knn"), True, "knn")
            confidence = query_flag(request.query_params.get("confidence"), False, "confidence")
            points = parse_scan(await request.body(), "the scan", record=self.record)
        except ScanFormatError as exc:
            return JSONResponse({"detail": f"The scan is malformed: {exc.problem}."}, 400)
        except ValueError as exc:
            return JSONResponse({"detail": f"{str(exc).capitalize()}."}, 400)
        start = time.perf_counter()
        result = await self.label_one(ScanRequest(points, knn, confidence))
        if isinstance(result, str):
            return JSONResponse({"detail": f"The scan cannot be projected: {result}."}, 422)
        body, headers = encode_labels(result)
        headers["Server-Timing"] = f"label;dur={(time.perf_counter() - start) * 1000:.1f}"
        return Response(body, media_type=OCTET, headers=headers)

    def check_health(self) -> None:
        """Serve's health check: a replica whose last network pass failed is replaced."""
        if self._failure is not None:
            raise RuntimeError(f"the last network pass failed: {self._failure}")


def deployment_options(spec: InferenceSpec, batch_wait_ms: float, gpus: float) -> dict[str, Any]:
    """The deployment's defaults: backpressure sized to the batch (one batch running, one
    gathering), autoscaling on the requests in flight per replica, health checks, and the batch
    size and wait as the replicas' `user_config`."""
    batch_size = spec.batch_size
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
        "user_config": {"batch_size": batch_size, "batch_wait_ms": batch_wait_ms},
    }


def build_app(args: Mapping[str, object]) -> serve.Application:
    """The application for Serve config arguments: `InferenceSpec` fields by name and
    `batch_wait_ms`; an unknown or bad argument is one sentence naming it, before any replica
    starts."""
    values = {k: v for k, v in args.items() if k not in APP_ARGUMENTS}
    try:
        spec = InferenceSpec.from_mapping(values, where=" of the rangeret Serve application")
    except InferenceSpecError as exc:
        raise ValueError(str(exc)) from exc
    wait = args.get("batch_wait_ms", DEFAULT_BATCH_WAIT_MS)
    if isinstance(wait, bool) or not isinstance(wait, int | float):
        raise ValueError(
            f"batch_wait_ms of the rangeret Serve application takes a number, got {wait!r}"
        )
    if wait < 0:
        raise ValueError(f"batch_wait_ms must not be negative, got {wait:g}")
    resources = read_resources() if spec.device == "auto" else ClusterResources()
    options = deployment_options(spec, float(wait), replica_gpus(spec.device, resources))
    return serve.deployment(**options)(ScanModel).bind(spec.to_mapping())
