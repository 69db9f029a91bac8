"""The FastAPI app of the gateway: every endpoint of DESIGN section 8, its errors and its token rule.

`create_app` takes the settings, a started worker pool and a job executor; the app owns the
request batcher, the job store and runner, and the metrics. Every error is answered as
`{"detail": "<one sentence>"}`; with RANGERET_API_TOKEN set, every /v1 request needs
`Authorization: Bearer TOKEN` (/healthz, /metrics and the API description do not).
"""

from __future__ import annotations

import asyncio
import hmac
import json
import logging
from collections.abc import AsyncIterator, Sequence
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Annotated, Any, Protocol

import numpy as np
from fastapi import APIRouter, Depends, FastAPI, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.utils import get_openapi
from fastapi.responses import FileResponse, JSONResponse, Response
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException

from rangeret.io import POINT_BYTES, ScanFormatError, parse_scan
from rangeret.labels import LabelConfig, semantickitti
from rangeret.layout import DatasetLayoutError, resolve_sequences
from rangeret.predict import list_scans
from service.archives import ArchiveError, ArchiveLimits, extract_archive
from service.batching import BackendError, ScanBackend, ScanBatcher
from service.errors import ApiError, default_sentence, error_responses, validation_sentence
from service.jobs import JobExecutor, JobManager, JobRecord, JobStore
from service.metrics import GatewayMetrics, MetricsMiddleware
from service.schemas import (
    DatasetJobRequest,
    ErrorResponse,
    Health,
    JobCreated,
    JobList,
    JobMetrics,
    JobState,
    JobStatus,
    ScanLabels,
)
from service.settings import Settings
from service.uploads import drain, media_type, read_body, receive_archive

log = logging.getLogger(__name__)

OCTET = "application/octet-stream"
_BINARY = {"schema": {"type": "string", "format": "binary"}}
_BEARER = HTTPBearer(auto_error=False, description="the gateway's RANGERET_API_TOKEN")


class WorkerPool(ScanBackend, Protocol):
    """What the gateway needs from `workers.pool.ScanPool` / `LocalScanPool`."""

    backend: str

    def health(self) -> dict:
        """The workers' state."""
        ...


@dataclass
class Gateway:
    """Everything the endpoints use, built by `create_app` and started by its lifespan."""

    settings: Settings
    pool: WorkerPool
    executor: JobExecutor
    label_config: LabelConfig
    checkpoint_sha256: str | None
    dispatchers: int
    metrics: GatewayMetrics = field(default_factory=GatewayMetrics)
    batcher: ScanBatcher | None = None
    jobs: JobManager | None = None

    async def start(self) -> None:
        """Open the job store, recover and start the runner, start the batcher."""
        settings = self.settings
        settings.jobs_folder.mkdir(parents=True, exist_ok=True)
        store = JobStore(settings.database_path)
        self.jobs = JobManager(
            store,
            self.executor,
            settings.jobs_folder,
            settings.retention.total_seconds(),
            label_config=self.label_config,
            checkpoint_sha256=self.checkpoint_sha256,
            on_scans=self.metrics.job_scans,
        )
        await asyncio.to_thread(self.jobs.start)
        self.batcher = ScanBatcher(
            self.pool,
            batch_size=settings.batch_size,
            max_wait=settings.batch_wait_ms / 1000,
            dispatchers=self.dispatchers,
            on_batch=self.metrics.observe_batch,
        )
        await self.batcher.start()

    async def stop(self) -> None:
        """Stop the batcher and the job runner (a running job resumes at the next start)."""
        if self.batcher is not None:
            await self.batcher.stop()
        if self.jobs is not None:
            await asyncio.to_thread(self.jobs.stop)
            self.jobs.store.close()

    def manager(self) -> JobManager:
        """The job manager (the app is started)."""
        if self.jobs is None:
            raise ApiError(503, "The gateway is starting; try again in a moment.")
        return self.jobs


def _gateway(request: Request) -> Gateway:
    return request.app.state.gateway


# Helpers -----------------------------------------------------------------------------------


def wants_json(accept: str | None) -> bool:
    """Whether the Accept header prefers application/json to the raw label bytes."""
    if not accept:
        return False
    weights: dict[str, float] = {}
    for item in accept.split(","):
        kind, *params = (p.strip() for p in item.split(";"))
        q = 1.0
        for param in params:
            if param.lower().startswith("q="):
                try:
                    q = float(param[2:])
                except ValueError:
                    q = 0.0
        weights[kind.lower()] = max(q, weights.get(kind.lower(), 0.0))
    as_json = weights.get("application/json", 0.0)
    if as_json <= 0:
        return False
    if OCTET not in weights:
        return True
    return as_json > weights[OCTET]


def _iso(ts: float | None) -> datetime | None:
    return datetime.fromtimestamp(ts, tz=timezone.utc) if ts is not None else None


def job_status(record: JobRecord) -> JobStatus:
    """The API form of a stored job."""
    base = f"/v1/jobs/{record.id}"
    return JobStatus(
        id=record.id,
        state=record.state,
        kind=record.kind,
        sequences=record.sequences,
        total=record.total,
        done=record.done,
        failed=record.failed,
        metrics=JobMetrics(**record.metrics) if record.metrics else None,
        errors=record.errors,
        reason=record.reason,
        created=_iso(record.created),
        started=_iso(record.started),
        finished=_iso(record.finished),
        status_url=base,
        predictions_url=f"{base}/predictions",
        report_url=f"{base}/report",
    )


def resolve_dataset(text: str, roots: Sequence[Path]) -> Path:
    """The dataset folder named by a job request: 403 outside the data roots, 404 when absent."""
    if not roots:
        raise ApiError(
            403,
            "No data roots are configured (RANGERET_DATA_ROOTS), so no dataset on the server can be used.",
        )
    try:
        path = Path(text)
        candidates = [path] if path.is_absolute() else [root / path for root in roots]
        inside = [c.resolve() for c in candidates]
    except (ValueError, OSError) as exc:
        raise ApiError(400, f"The dataset path is not a usable path ({exc}).") from exc
    inside = [p for p in inside if any(p.is_relative_to(root) for root in roots)]
    if not inside:
        raise ApiError(403, "The dataset path is outside the configured data roots.")
    for candidate in inside:
        if candidate.is_dir():
            return candidate
    raise ApiError(404, "There is no dataset folder at that path under the data roots.")


def _class_counts(labels: np.ndarray, config: LabelConfig) -> dict[str, int]:
    counts = np.bincount(config.to_class(labels), minlength=config.num_classes)
    return {config.class_names[c]: int(n) for c, n in enumerate(counts) if n}


# Routes ------------------------------------------------------------------------------------


def _v1_router(settings: Settings) -> APIRouter:
    """The /v1 endpoints, behind the bearer token when one is configured."""
    dependencies = []
    if settings.token is not None:
        expected = settings.token.encode()

        async def require_token(
            credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_BEARER)],
        ) -> None:
            if credentials is None:
                raise ApiError(
                    401,
                    "This endpoint needs the header 'Authorization: Bearer <token>'.",
                    {"WWW-Authenticate": "Bearer"},
                )
            if not hmac.compare_digest(credentials.credentials.encode(), expected):
                raise ApiError(401, "The bearer token is wrong.", {"WWW-Authenticate": "Bearer"})

        dependencies.append(Depends(require_token))
    auth = (401,) if settings.token is not None else ()
    router = APIRouter(prefix="/v1", dependencies=dependencies)

    @router.post(
        "/scans",
        summary="Label one scan",
        description=(
            "The body is the raw bytes of one `.bin` scan (float32 x, y, z, remission per point). "
            "The answer is the raw `.label` bytes (uint32 raw SemanticKITTI ids, one per point), or "
            "with `Accept: application/json` the labels with their class counts. Concurrent requests "
            "are labelled together in batches."
        ),
        response_class=Response,
        responses={
            200: {
                "description": "One raw label per point",
                "content": {
                    OCTET: _BINARY,
                    "application/json": {"schema": ScanLabels.model_json_schema()},
                },
            },
            **error_responses(400, *auth, 413, 415, 503),
        },
        openapi_extra={"requestBody": {"required": True, "content": {OCTET: _BINARY}}},
    )
    async def label_scan(
        request: Request,
        knn: bool = Query(default=True, description="refine labels with kNN over the point cloud"),
    ) -> Response:
        gw = _gateway(request)
        limits = gw.settings
        if media_type(request) != OCTET:
            await drain(request, limits.max_body_bytes)
            raise ApiError(
                415,
                f"Send the scan as {OCTET}, not {media_type(request) or 'without a Content-Type'}.",
            )
        body = await read_body(request, limits.max_body_bytes)
        if len(body) // POINT_BYTES > limits.max_points:
            raise ApiError(
                413,
                f"The scan has {len(body) // POINT_BYTES:,} points, over the limit of {limits.max_points:,}.",
            )
        try:
            points = await asyncio.to_thread(parse_scan, body, "the scan")
        except ScanFormatError as exc:
            raise ApiError(400, f"The scan is malformed: {exc.problem}.") from exc
        if gw.batcher is None:
            raise ApiError(503, "The gateway is starting; try again in a moment.")
        try:
            labels = await gw.batcher.label(points, knn)
        except BackendError as exc:
            raise ApiError(503, str(exc)) from exc
        gw.metrics.scans.labels(source="request").inc()
        gw.metrics.points.inc(len(points))
        raw = labels.astype("<u4", copy=False)
        if wants_json(request.headers.get("accept")):
            body = ScanLabels(
                num_points=len(raw),
                labels=raw.tolist(),
                class_counts=_class_counts(raw, gw.label_config),
            )
            return JSONResponse(body.model_dump())
        return Response(raw.tobytes(), media_type=OCTET)

    job_body = {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "properties": {
                        "archive": {
                            "type": "string",
                            "format": "binary",
                            "description": ".zip, .tar or .tar.gz with sequences/XX/velodyne/*.bin "
                            "and optional sequences/XX/labels/*.label",
                        }
                    },
                    "required": ["archive"],
                }
            },
            "application/json": {"schema": DatasetJobRequest.model_json_schema()},
        },
    }

    @router.post(
        "/jobs",
        summary="Start a job over sequences",
        description=(
            "Either upload an archive (multipart field `archive`) laid out as sequences/XX/velodyne/*.bin "
            "with optional sequences/XX/labels/*.label, or name a dataset under the configured data roots "
            "in JSON. The job predicts every scan; with labels it also evaluates them."
        ),
        status_code=202,
        response_model=JobCreated,
        responses=error_responses(400, *auth, 403, 404, 413, 415),
        openapi_extra={"requestBody": job_body},
    )
    async def create_job(request: Request) -> JSONResponse:
        gw = _gateway(request)
        kind = media_type(request)
        if kind == "multipart/form-data":
            record = await _archive_job(request, gw)
        elif kind == "application/json":
            record = await _dataset_job(request, gw)
        else:
            await drain(request, gw.settings.max_body_bytes)
            raise ApiError(
                415,
                "Send a job as multipart/form-data (an 'archive' file) or as application/json (a dataset).",
            )
        created = JobCreated(id=record.id, status_url=f"/v1/jobs/{record.id}")
        return JSONResponse(
            created.model_dump(), status_code=202, headers={"Location": created.status_url}
        )

    @router.get(
        "/jobs", summary="List jobs", response_model=JobList, responses=error_responses(*auth)
    )
    async def list_jobs(request: Request) -> JobList:
        jobs = _gateway(request).manager()
        records = await asyncio.to_thread(jobs.store.list)
        return JobList(jobs=[job_status(r) for r in records])

    @router.get(
        "/jobs/{job_id}",
        summary="A job's state and progress",
        response_model=JobStatus,
        responses=error_responses(*auth, 404),
    )
    async def get_job(request: Request, job_id: str) -> JobStatus:
        return job_status(_record_or_404(request, job_id))

    @router.get(
        "/jobs/{job_id}/predictions",
        summary="A succeeded job's predictions (zip)",
        description="A zip of sequences/XX/predictions/*.label with directory entries for the job's sequences.",
        response_class=FileResponse,
        responses={
            200: {
                "description": "The predictions archive",
                "content": {"application/zip": _BINARY},
            },
            **error_responses(*auth, 404, 409),
        },
    )
    async def get_predictions(request: Request, job_id: str) -> FileResponse:
        record = _succeeded_or_409(request, job_id)
        if not record.predictions or not Path(record.predictions).is_file():
            raise ApiError(404, "The job's predictions are no longer on the server.")
        return FileResponse(
            record.predictions, media_type="application/zip", filename=f"{job_id}-predictions.zip"
        )

    @router.get(
        "/jobs/{job_id}/report",
        summary="A succeeded labelled job's evaluation report",
        description="The evaluation JSON of `rangeret evaluate`: miou, accuracy, iou by class, confusion[pred][gt].",
        response_class=FileResponse,
        responses={
            200: {
                "description": "The evaluation report",
                "content": {"application/json": {"schema": {"type": "object"}}},
            },
            **error_responses(*auth, 404, 409),
        },
    )
    async def get_report(request: Request, job_id: str) -> FileResponse:
        record = _succeeded_or_409(request, job_id)
        if not record.report:
            raise ApiError(404, "The job's scans had no labels, so it has no evaluation report.")
        if not Path(record.report).is_file():
            raise ApiError(404, "The job's report is no longer on the server.")
        return FileResponse(record.report, media_type="application/json")

    @router.delete(
        "/jobs/{job_id}",
        summary="Cancel a job and remove its files",
        description="A queued or running job is cancelled and its files removed; a finished job's files and record are removed.",
        response_model=JobStatus,
        responses=error_responses(*auth, 404),
    )
    async def delete_job(request: Request, job_id: str) -> JobStatus:
        jobs = _gateway(request).manager()
        record = await asyncio.to_thread(jobs.cancel, job_id)
        if record is None:
            raise ApiError(404, f"There is no job {job_id[:64]!r}.")
        return job_status(record)

    return router


def _record_or_404(request: Request, job_id: str) -> JobRecord:
    record = _gateway(request).manager().store.get(job_id)
    if record is None:
        raise ApiError(404, f"There is no job {job_id[:64]!r}.")
    return record


def _succeeded_or_409(request: Request, job_id: str) -> JobRecord:
    record = _record_or_404(request, job_id)
    if record.state is not JobState.succeeded:
        raise ApiError(
            409, f"The job is {record.state.value}, and results exist only once it has succeeded."
        )
    return record


async def _archive_job(request: Request, gw: Gateway) -> JobRecord:
    """Receive, check and extract an uploaded archive into a new job's folder; queue the job."""
    jobs = gw.manager()
    settings = gw.settings
    job_id, folder = await asyncio.to_thread(jobs.new_job)
    try:
        upload = folder / "upload.part"
        await receive_archive(request, upload, settings.max_archive_bytes)
        limits = ArchiveLimits(
            settings.max_archive_bytes, settings.max_archive_members, settings.max_points
        )
        try:
            found = await asyncio.to_thread(extract_archive, upload, folder / "data", limits)
        except ArchiveError as exc:
            raise ApiError(exc.status_code, str(exc)) from exc
        finally:
            upload.unlink(missing_ok=True)
        return jobs.submit(job_id, "archive", found.root, found.sequences)
    except BaseException:
        await asyncio.to_thread(jobs.remove_files, job_id)
        raise


async def _dataset_job(request: Request, gw: Gateway) -> JobRecord:
    """Check a dataset job request (roots, sequences, layout) and queue the job."""
    jobs = gw.manager()
    body = await read_body(request, gw.settings.max_body_bytes)
    try:
        data = json.loads(body)
    except (ValueError, UnicodeDecodeError) as exc:
        raise ApiError(400, "The request body is not valid JSON.") from exc
    try:
        job = DatasetJobRequest.model_validate(data)
    except ValidationError as exc:
        raise ApiError(400, validation_sentence(exc.errors(), "body")) from exc
    root = resolve_dataset(job.dataset, gw.settings.data_roots)
    try:
        sequences = resolve_sequences(job.split, job.sequences, gw.label_config)
        await asyncio.to_thread(list_scans, root, sequences)
    except (DatasetLayoutError, ValueError) as exc:
        raise ApiError(400, f"The dataset cannot be used: {str(exc)[:400]}") from exc
    job_id, _ = await asyncio.to_thread(jobs.new_job)
    return jobs.submit(job_id, "dataset", root, sequences)


# App -----------------------------------------------------------------------------------------


def _error(status_code: int, detail: str, headers: dict[str, str] | None = None) -> JSONResponse:
    return JSONResponse(
        ErrorResponse(detail=detail).model_dump(), status_code=status_code, headers=headers
    )


def _install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(ApiError)
    async def api_error(_: Request, exc: ApiError) -> JSONResponse:
        return _error(exc.status_code, exc.detail, exc.headers)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(_: Request, exc: StarletteHTTPException) -> JSONResponse:
        return _error(
            exc.status_code,
            default_sentence(exc.status_code, exc.detail),
            getattr(exc, "headers", None),
        )

    @app.exception_handler(RequestValidationError)
    async def invalid_request(_: Request, exc: RequestValidationError) -> JSONResponse:
        return _error(400, validation_sentence(exc.errors()))

    @app.exception_handler(Exception)
    async def unexpected(_: Request, exc: Exception) -> JSONResponse:
        log.error("unexpected error", exc_info=exc)
        return _error(500, "The gateway failed unexpectedly; the error is in its log.")


def _openapi(app: FastAPI) -> dict[str, Any]:
    """The OpenAPI description, with 400 (not FastAPI's 422) for request validation."""
    if app.openapi_schema:
        return app.openapi_schema
    schema = get_openapi(
        title=app.title, version=app.version, description=app.description, routes=app.routes
    )
    error_ref = {"$ref": "#/components/schemas/ErrorResponse"}
    for path in schema.get("paths", {}).values():
        for operation in path.values():
            responses = operation.get("responses", {})
            responses.pop("422", None)
            queries = [p for p in operation.get("parameters", []) if p.get("in") == "query"]
            if queries or operation.get("requestBody"):
                responses.setdefault(
                    "400",
                    {
                        "description": "Malformed request",
                        "content": {"application/json": {"schema": error_ref}},
                    },
                )
    components = schema.setdefault("components", {}).setdefault("schemas", {})
    components.pop("HTTPValidationError", None)
    components.pop("ValidationError", None)
    components["ErrorResponse"] = ErrorResponse.model_json_schema()
    app.openapi_schema = schema
    return schema


def create_app(
    settings: Settings,
    pool: WorkerPool,
    executor: JobExecutor,
    label_config: LabelConfig | None = None,
    checkpoint_sha256: str | None = None,
    dispatchers: int = 1,
) -> FastAPI:
    """The gateway app over a ready worker pool; refuses a non-loopback host without a token."""
    problem = settings.address_problem()
    if problem:
        raise ValueError(problem)
    gateway = Gateway(
        settings, pool, executor, label_config or semantickitti(), checkpoint_sha256, dispatchers
    )

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        await gateway.start()
        try:
            yield
        finally:
            await gateway.stop()

    app = FastAPI(
        title="RangeRet gateway",
        version="1.0",
        description=(
            "LiDAR semantic segmentation with RangeRet over HTTP: label single scans, or run jobs over "
            "whole sequences (uploaded archives or datasets under the data roots) and download the "
            'predictions and the per-class IoU. Errors are `{"detail": "<one sentence>"}`.'
        ),
        lifespan=lifespan,
    )
    app.state.gateway = gateway
    app.add_middleware(MetricsMiddleware, metrics=lambda: gateway.metrics)
    _install_error_handlers(app)
    app.include_router(_v1_router(settings))

    @app.get(
        "/healthz",
        summary="Health of the gateway and its workers",
        response_model=Health,
        responses={503: {"model": Health, "description": "The worker backend is unavailable"}},
    )
    async def healthz() -> JSONResponse:
        state = await asyncio.to_thread(gateway.pool.health)
        ok = bool(state.get("ok"))
        body = Health(
            status="ok" if ok else "unavailable",
            backend=state.get("backend", gateway.pool.backend),
            workers=state.get("actors", []),
            queue_depth=gateway.batcher.depth() if gateway.batcher else 0,
            batch_size=settings.batch_size,
            batch_wait_ms=settings.batch_wait_ms,
            checkpoint_sha256=checkpoint_sha256,
            error=state.get("error"),
        )
        return JSONResponse(body.model_dump(mode="json"), status_code=200 if ok else 503)

    @app.get(
        "/metrics",
        summary="Prometheus metrics",
        response_class=Response,
        responses={
            200: {
                "description": "Prometheus text exposition",
                "content": {"text/plain": {"schema": {"type": "string"}}},
            }
        },
    )
    async def metrics() -> Response:
        depth = gateway.batcher.depth() if gateway.batcher else 0
        counts = await asyncio.to_thread(gateway.jobs.store.counts) if gateway.jobs else {}
        return Response(
            gateway.metrics.render(depth, counts), media_type=gateway.metrics.content_type
        )

    app.openapi = lambda: _openapi(app)
    return app
