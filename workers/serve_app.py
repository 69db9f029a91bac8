"""The Ray Serve application that labels single scans: `workers.serve_app:build_app`.

    serve deploy config.yaml      # import_path: workers.serve_app:build_app, args: {checkpoint: ...}

The application is one deployment, `ScanModel`, whose replicas (one GPU each where the cluster
has or can add GPUs) serve one or several models by name (`workers.serve_arguments` reads the
arguments). A request names its model with Serve's `serve_multiplexed_model_id` header (none: the
default model); a replica keeps at most `max_num_models_per_replica` networks loaded, loading on
first use and unloading the least recently used one (`@serve.multiplexed`), and Serve routes a
request to a replica that has its model loaded. A replica holds no network of its own beyond
Serve's: its batches name their model by a weak reference (Serve's batcher keeps its last batch
until the next one), so an unloaded model's network is freed once its last request is answered,
and its memory handed back to the system before the next network is built. A loaded model answers
panoptic requests (`panoptic=true`) with the same network, its objects clustered as its spec's
`cluster_angle` and `min_cluster_points` say; other requests get classes only, whatever its
`panoptic`. Each replica gathers concurrent requests into
batches of up to `batch_size` scans of one model (`@serve.batch`) and answers in the exchange of
`workers.scan_wire` through a FastAPI app (`@serve.ingress`). `batch_size` and `batch_wait_ms`
reach the replicas as the deployment's `user_config`, so a Serve config that changes them there
reconfigures running replicas without reloading any network. Every model's checkpoint is read
once when the application is built, for the SHA-256, profile and network `/info` lists (a gateway
compares them with its own models when it starts); a replica refuses a checkpoint whose bytes have
changed since. Autoscaling, backpressure (`max_ongoing_requests`, `max_queued_requests`) and
health checks have defaults here that a Serve config's `deployments` entry overrides.
"""

import asyncio
import logging
import os
import time
import weakref
from collections.abc import Callable, Mapping
from typing import Any

import torch
from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse, Response
from ray import serve

from rangeret.exceptions import RangeRetError
from rangeret.inference.loaded_weights import RefusalLog, identify_weights, load_checked_weights
from rangeret.inference.model_set import ModelSet
from rangeret.inference.predictor import Predictor
from rangeret.inference.results import ScanOutcome
from rangeret.inference.runtime.memory import release_freed_memory
from rangeret.inference.scan_worker import ScanRequest, ScanWorker, use_cpus
from rangeret.inference.settings import ClusterSettings
from rangeret.inference.spec import InferenceSpec
from rangeret.io.scans import ScanFormatError, parse_scan
from workers.cluster import read_resources
from workers.scan_wire import INFO_PATH, OCTET, SCANS_PATH, encode_labels, query_flag
from workers.serve_arguments import (
    DEFAULT_BATCH_WAIT_MS,
    WHERE,
    AppArguments,
    read_arguments,
)
from workers.sizing import ClusterResources, replica_gpus

log = logging.getLogger(__name__)

DEPLOYMENT = "ScanModel"
#: Requests waiting for a replica beyond which Serve answers 503 (backpressure).
DEFAULT_MAX_QUEUED = 128
#: How often Serve calls a replica's health check, and how long it may take.
HEALTH_CHECK_PERIOD_S = 10.0
HEALTH_CHECK_TIMEOUT_S = 30.0

api = FastAPI(title="rangeret Serve application", openapi_url=None, docs_url=None)


@api.exception_handler(404)
async def _no_such_operation(request: Request, exc: Exception) -> JSONResponse:
    return JSONResponse({"detail": f"No such operation: {request.method} {request.url.path}."}, 404)


class ReplicaModel:
    """One model loaded on a replica: its name and scan workers, one for classes only and one
    that also finds objects (built on the first panoptic request, sharing the network). Serve
    calls `__del__` when it unloads the model, and `on_unload` tells the replica."""

    def __init__(
        self,
        name: str,
        predictor: Predictor,
        on_unload: Callable[[Any], None],
        clustering: ClusterSettings | None = None,
    ) -> None:
        self.name = name
        self.worker = ScanWorker(predictor.with_clustering(None))
        self.clustering = clustering or ClusterSettings()
        self._panoptic: ScanWorker | None = None
        self.on_unload = on_unload

    @property
    def panoptic_refusal(self) -> str | None:
        """Why the model cannot find objects (its profile names no thing class), or None."""
        return self.worker.profile.panoptic_refusal()

    def worker_for(self, panoptic: bool) -> ScanWorker:
        """The scan worker of a request: with `panoptic`, the one whose labels are the
        benchmark's panoptic labels and whose answers carry the objects."""
        if not panoptic:
            return self.worker
        if self._panoptic is None:
            self._panoptic = ScanWorker(self.worker.predictor.with_clustering(self.clustering))
        return self._panoptic

    def __del__(self) -> None:
        self.on_unload(self)


@serve.ingress(api)
class ScanModel:
    """One replica: its models (loaded on first use, at most `max_per_replica` at once), a
    batcher in front of them, and the HTTP exchange."""

    def __init__(
        self,
        models: Mapping[str, Any],
        built: Mapping[str, Mapping[str, str | None]],
        max_per_replica: int,
    ) -> None:
        import ray

        self.models = ModelSet.from_mapping(models, source="the application's models")
        self.built = built
        self.max_per_replica = max_per_replica
        use_cpus(ray.get_runtime_context().get_assigned_resources().get("CPU", 1.0))
        self.batch_size = 1
        self._loaded: dict[str, int] = {}
        self._failure: str | None = None
        self._refusals = RefusalLog(log)
        self._load_model = serve.multiplexed(max_num_models_per_replica=max_per_replica)(
            self._loader()
        )
        # The default model is loaded now, so a replica is ready when it can serve it; Serve's
        # multiplexer takes it over on its first request.
        self._preloaded: ReplicaModel | None = self._load(self.models.default)

    def _loader(self) -> Callable[[str], Any]:
        """Serve's multiplexed loader: the model `name`, its network loaded in a worker thread
        (the one loaded at start, for the default model's first request)."""

        async def load_model(name: str) -> ReplicaModel:
            preloaded, self._preloaded = self._preloaded, None
            if preloaded is not None and preloaded.name == name:
                return preloaded
            del preloaded
            return await asyncio.to_thread(self._load, name)

        return load_model

    def _load(self, name: str) -> ReplicaModel:
        """The model `name`'s network, whose checkpoint must be the one the application was
        built with."""
        started = time.perf_counter()
        release_freed_memory()  # what the networks Serve unloaded held
        spec = self.models.spec(name)
        built = self.built[name]
        when, remedy = "the application was built", "deploy it again"
        weights = load_checked_weights(
            spec, built.get("checkpoint_sha256"), f"model {name}", f"when {when}", remedy
        )
        predictor = Predictor(weights, spec)
        predictor.weights.identity.check_same(built, name, when, remedy)
        clustering = ClusterSettings(spec.cluster_angle, spec.min_cluster_points)
        model = ReplicaModel(name, predictor, self._unloaded, clustering)
        self._loaded[name] = id(model)
        log.info("model %s loaded in %.2f s", name, time.perf_counter() - started)
        return model

    def _unloaded(self, model: ReplicaModel) -> None:
        """Forget a model Serve unloaded (unless it has been loaded again since)."""
        if self._loaded.get(model.name) == id(model):
            del self._loaded[model.name]

    def reconfigure(self, config: Mapping[str, Any]) -> None:
        """Serve's `user_config`: the batch size and wait, changed in place on running replicas."""
        size = int(config.get("batch_size", 1))
        self.label_one.set_max_batch_size(size)
        self.label_one.set_batch_wait_timeout_s(
            float(config.get("batch_wait_ms", DEFAULT_BATCH_WAIT_MS)) / 1000
        )
        self.batch_size = size

    @serve.batch(max_batch_size=1, batch_wait_timeout_s=DEFAULT_BATCH_WAIT_MS / 1000)
    async def label_one(
        self,
        models: list[weakref.ref[ReplicaModel]],
        requests: list[ScanRequest],
        panoptic: list[bool],
    ) -> list[ScanOutcome]:
        """A batch of requests labelled, one network pass per model, task and set of equal
        options (Serve gathers the requests of one model into a batch); each request names its
        model by a weak reference, alive while the request holds the model."""
        return await asyncio.to_thread(self._label, [ref() for ref in models], requests, panoptic)

    def _label(
        self,
        models: list[ReplicaModel | None],
        requests: list[ScanRequest],
        panoptic: list[bool],
    ) -> list[ScanOutcome]:
        results: list[ScanOutcome] = [""] * len(requests)
        groups: dict[tuple[int, bool], list[int]] = {}
        for i, (model, task) in enumerate(zip(models, panoptic, strict=True)):
            groups.setdefault((id(model), task), []).append(i)
        try:
            for (_, task), indices in groups.items():
                model = models[indices[0]]
                assert model is not None  # its request holds it until answered
                worker = model.worker_for(task)
                labelled = worker.label_requests([requests[i] for i in indices])
                for i, result in zip(indices, labelled, strict=True):
                    results[i] = result
        except Exception as exc:
            self._failure = f"{type(exc).__name__}: {exc}"
            raise
        self._failure = None
        return results

    @api.get(INFO_PATH)
    def info(self) -> dict:
        """What this replica serves: every model (as built) and whether it is loaded here."""
        return {
            "pid": os.getpid(),
            "threads": torch.get_num_threads(),
            "batch_size": self.batch_size,
            "default": self.models.default,
            "max_num_models_per_replica": self.max_per_replica,
            "models": [
                {"id": name, **self.built[name], "loaded": name in self._loaded}
                for name in self.models.names
            ],
        }

    @api.post(SCANS_PATH)
    async def scans(self, request: Request) -> Response:
        """The body's scan labelled by the request's model, in the exchange of
        `workers.scan_wire`."""
        name = serve.get_multiplexed_model_id() or self.models.default
        if name not in self.built:
            known = ", ".join(self.models.names)
            return JSONResponse(
                {"detail": f"There is no model {name[:64]!r}; this application serves {known}."},
                404,
            )
        try:
            knn = query_flag(request.query_params.get("knn"), True, "knn")
            confidence = query_flag(request.query_params.get("confidence"), False, "confidence")
            panoptic = query_flag(request.query_params.get("panoptic"), False, "panoptic")
            body = await request.body()
        except ValueError as exc:
            return JSONResponse({"detail": f"{str(exc).capitalize()}."}, 400)
        start = time.perf_counter()
        try:
            model = await self._load_model(name)
        except RangeRetError as exc:  # its checkpoint changed or went since the build
            reason = self._refusals.note(name, exc)
            return JSONResponse({"detail": f"Model {name} cannot be loaded again: {reason}."}, 503)
        except (RuntimeError, OSError) as exc:
            return JSONResponse({"detail": f"Model {name} cannot be loaded: {exc}."}, 500)
        if panoptic and model.panoptic_refusal is not None:
            return JSONResponse(
                {"detail": f"Model {name} finds no objects: {model.panoptic_refusal}."}, 400
            )
        try:
            points = parse_scan(body, "the scan", record=model.worker.profile.points)
        except ScanFormatError as exc:
            return JSONResponse({"detail": f"The scan is malformed: {exc.problem}."}, 400)
        result = await self.label_one(
            weakref.ref(model), ScanRequest(points, knn, confidence), panoptic
        )
        if isinstance(result, str):
            return JSONResponse({"detail": f"The scan cannot be projected: {result}."}, 422)
        body, headers = encode_labels(result)
        headers["Server-Timing"] = f"label;dur={(time.perf_counter() - start) * 1000:.1f}"
        return Response(body, media_type=OCTET, headers=headers)

    def check_health(self) -> None:
        """Serve's health check: a replica whose last network pass failed is replaced."""
        if self._failure is not None:
            raise RuntimeError(f"the last network pass failed: {self._failure}")


def deployment_options(batch_size: int, batch_wait_ms: float, gpus: float) -> dict[str, Any]:
    """The deployment's defaults: backpressure sized to the batch (one batch running, one
    gathering), autoscaling on the requests in flight per replica, health checks, and the batch
    size and wait as the replicas' `user_config`."""
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


def built_models(models: ModelSet) -> dict[str, dict[str, str | None]]:
    """Each model's identity as `/info` lists it (checkpoint SHA-256, profile, network), its
    checkpoint read once now; a model whose weights cannot be served is one `ValueError` naming
    it."""
    built = {}
    for name, spec in models:
        try:
            built[name] = identify_weights(spec).describe()
        except RangeRetError as exc:
            raise ValueError(f"model {name}{WHERE}: {exc}") from exc
    return built


def replica_gpu_count(specs: list[InferenceSpec]) -> float:
    """GPUs each replica asks for: one where any model runs on a GPU (`cuda`, or `auto` on a
    cluster that has or can add GPUs)."""
    auto = any(spec.device == "auto" for spec in specs)
    resources = read_resources() if auto else ClusterResources()
    return max(replica_gpus(spec.device, resources) for spec in specs)


def build_app(args: Mapping[str, object]) -> serve.Application:
    """The application for Serve config arguments (`workers.serve_arguments`); an unknown or bad
    argument, or a checkpoint that cannot be served, is one sentence naming it, before any
    replica starts."""
    checked: AppArguments = read_arguments(args)
    models = checked.models
    built = built_models(models)
    gpus = replica_gpu_count([spec for _, spec in models])
    options = deployment_options(checked.batch_size, checked.batch_wait_ms, gpus)
    return serve.deployment(**options)(ScanModel).bind(
        models.to_mapping(), built, checked.max_per_replica
    )
