"""/v1/jobs: start a job over whole sequences, list and follow jobs, fetch results, cancel.

A job comes from an uploaded archive (`POST /v1/jobs/uploads`, multipart field `archive`) or names
a dataset under the data roots (`POST /v1/jobs`, JSON; that operation also takes the upload form,
which the API description leaves out so that client generators see one body per operation). The
routes parse the request and reply; `service.jobs.intake` prepares, checks and queues a new job,
and `service.jobs.results` names a job's result files. The job store is only ever called through
a worker thread, never on the event loop.
"""

from __future__ import annotations

import asyncio
import json
from datetime import datetime, timezone
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Query, Request
from fastapi.responses import FileResponse, JSONResponse
from pydantic import ValidationError

from service.gateway import Gateway
from service.http.bodies import (
    declared_length,
    media_type,
    read_body,
    receive_archive,
    refused_body,
)
from service.http.dependencies import GatewayDep, JobsDep
from service.http.errors import ApiError, error_responses, validation_sentence
from service.jobs import JobManager, JobRecord
from service.jobs.errors import JobInputError, JobRefused
from service.jobs.intake import JobIntake, check_panoptic
from service.jobs.results import plot_path, report_plots
from service.models.catalog import MODEL_QUERY, ModelEntry
from service.routes.job_errors import answered, job_error_answer
from service.schemas import (
    DatasetJobRequest,
    JobCreated,
    JobList,
    JobMetrics,
    JobState,
    JobStatus,
    file_content,
)

router = APIRouter(prefix="/v1", tags=["jobs"])

MULTIPART = "multipart/form-data"
_DATASET_BODY = {
    "required": True,
    "content": {"application/json": {"schema": {"$ref": "#/components/schemas/DatasetJobRequest"}}},
}
_UPLOAD_BODY = {
    "required": True,
    "content": {MULTIPART: {"schema": {"$ref": "#/components/schemas/ArchiveUpload"}}},
}
#: The errors of every operation that reads a job.
_READ_ERRORS = error_responses(400, 404, 503)
#: The errors of the operations that read a succeeded job's results.
_RESULT_ERRORS = error_responses(400, 404, 409, 503)
#: The errors of both operations that start a job (the upload's 404 aside).
_START_DESCRIBED = {
    400: "Malformed request or archive, or a Host the gateway does not answer to",
    403: "A dataset path outside the configured data roots, or a request from another "
    "origin's page",
    404: "No dataset folder at that path under the data roots, or no model of that name",
}


def _iso(ts: float | None) -> datetime | None:
    return datetime.fromtimestamp(ts, tz=timezone.utc) if ts is not None else None


def job_status(record: JobRecord, default_model: str) -> JobStatus:
    """The API form of a stored job, a job from before models being the default model's (it
    lists the job's plots: call it in a worker thread)."""
    base = f"/v1/jobs/{record.id}"
    return JobStatus(
        id=record.id,
        state=record.state,
        kind=record.kind,
        model=record.model or default_model,
        sequences=record.sequences,
        version=record.version,
        split=record.split,
        panoptic=record.panoptic,
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
        plots=report_plots(record),
    )


@router.post(
    "/jobs",
    summary="Start a job over a dataset on the server",
    description=(
        "Name a dataset under the configured data roots in the layout of the model's profile "
        "(`model` in the body, the default model without it), and the split (by the profile's "
        "names) or sequences to run, with a tables profile's `version` (nuScenes) where the "
        "dataset holds several. The job predicts every scan with that model, writing its "
        "predictions where `rangeret predict` does; with labels it also evaluates them. With "
        "`panoptic: true` it finds the objects too, as `rangeret predict --panoptic` does: "
        "its zip is the profile's panoptic benchmark's archive and its report the panoptic "
        "scores. (An archive upload is `POST /v1/jobs/uploads`.)"
    ),
    operation_id="create_job",
    status_code=202,
    response_model=JobCreated,
    responses=error_responses(
        400, 403, 404, 408, 413, 415, 429, 503, 507, described=_START_DESCRIBED
    ),
    openapi_extra={"requestBody": _DATASET_BODY},
)
async def create_job(
    request: Request,
    gw: GatewayDep,
    jobs: JobsDep,
    model: Annotated[str | None, MODEL_QUERY] = None,
) -> JSONResponse:
    intake = JobIntake(jobs, gw.settings, gw.models)
    await _check_queue(request, gw, intake)
    kind = media_type(request)
    if kind == MULTIPART:
        entry = await _query_model(request, gw, model)
        record = await _archive_job(request, gw, intake, entry)
    elif kind == "application/json":
        dataset_request = await _dataset_request(request, gw)
        with answered():
            record = await intake.dataset_job(dataset_request)
    else:
        raise await _wrong_media(
            request,
            gw,
            "Send a dataset job as application/json, or upload an archive to /v1/jobs/uploads "
            "as multipart/form-data (an 'archive' file).",
        )
    return _created(record)


@router.post(
    "/jobs/uploads",
    summary="Start a job over an uploaded archive",
    description=(
        "Upload an archive (multipart field `archive`: .zip, .tar or .tar.gz) laid out as "
        "sequences/XX/velodyne/*.bin with optional sequences/XX/labels/*.label (for every "
        "folder profile), or for a nuScenes model as nuScenes ships it: one version's tables "
        "(v1.0-mini/*.json), samples/LIDAR_TOP/*.pcd.bin and optional "
        "lidarseg/<version>/*_lidarseg.bin. The scans hold the point records of the profile of "
        "the model `model` (the default model without it). The job predicts every scan with "
        "that model; with labels it also evaluates them. With `panoptic=true` it finds the "
        "objects too (an archive's labels are then its panoptic ground truth: SemanticKITTI's "
        "`.label` files with their instances, nuScenes-panoptic's `.npz` files)."
    ),
    operation_id="upload_job",
    status_code=202,
    response_model=JobCreated,
    responses=error_responses(
        400, 403, 404, 408, 413, 415, 429, 503, 507, described=_START_DESCRIBED
    ),
    openapi_extra={"requestBody": _UPLOAD_BODY},
)
async def upload_job(
    request: Request,
    gw: GatewayDep,
    jobs: JobsDep,
    model: Annotated[str | None, MODEL_QUERY] = None,
    panoptic: bool = Query(
        default=False,
        description="panoptic segmentation: also find the objects of the thing classes (refused "
        "for a model whose profile names none)",
    ),
) -> JSONResponse:
    intake = JobIntake(jobs, gw.settings, gw.models)
    await _check_queue(request, gw, intake)
    entry = await _query_model(request, gw, model)
    if media_type(request) != MULTIPART:
        raise await _wrong_media(
            request, gw, "Upload the archive as multipart/form-data, in a file field 'archive'."
        )
    return _created(await _archive_job(request, gw, intake, entry, panoptic))


async def _query_model(request: Request, gw: Gateway, name: str | None) -> ModelEntry:
    """The model an upload's `?model=` names (the default without it); 404, once the body is
    dropped, for one the gateway does not serve."""
    try:
        return gw.models.get(name)
    except ApiError as exc:
        raise await refused_body(request, gw.settings, exc, upload=True) from None


async def _check_queue(request: Request, gw: Gateway, intake: JobIntake) -> None:
    """429 while too many jobs wait, checked before the body is read (and dropped)."""
    try:
        await asyncio.to_thread(intake.check_queue)
    except JobRefused as exc:
        raise await refused_body(request, gw.settings, job_error_answer(exc)) from exc


async def _wrong_media(request: Request, gw: Gateway, detail: str) -> ApiError:
    """The 415 answer saying `detail`, once the body it refuses is dropped."""
    return await refused_body(request, gw.settings, ApiError(415, detail))


def _created(record: JobRecord) -> JSONResponse:
    """The 202 answer to a new job: its id, and where to follow it (also as `Location`)."""
    created = JobCreated(id=record.id, status_url=f"/v1/jobs/{record.id}", state=record.state)
    return JSONResponse(
        created.model_dump(mode="json"), status_code=202, headers={"Location": created.status_url}
    )


@router.get(
    "/jobs",
    summary="List jobs",
    operation_id="list_jobs",
    response_model=JobList,
    responses=error_responses(400, 503),
)
async def list_jobs(gw: GatewayDep, jobs: JobsDep) -> JobList:
    records = await asyncio.to_thread(jobs.store.list)
    default = gw.models.default
    return JobList(jobs=await asyncio.to_thread(lambda: [job_status(r, default) for r in records]))


@router.get(
    "/jobs/{job_id}",
    summary="A job's state and progress",
    operation_id="get_job",
    response_model=JobStatus,
    responses=_READ_ERRORS,
)
async def get_job(job_id: str, gw: GatewayDep, jobs: JobsDep) -> JobStatus:
    record = await _record_or_404(jobs, job_id)
    return await asyncio.to_thread(job_status, record, gw.models.default)


@router.get(
    "/jobs/{job_id}/predictions",
    summary="A succeeded job's predictions (zip)",
    description="A zip of sequences/XX/predictions/*.label with directory entries for the job's "
    "sequences; for a nuScenes model, the results folder lidarseg/<split>/*_lidarseg.bin with "
    "<split>/submission.json. A panoptic job's zip is the panoptic benchmark's: the same "
    "`.label` tree of panoptic labels, or nuScenes-panoptic's panoptic/<split>/*_panoptic.npz "
    "with <split>/submission.json.",
    operation_id="get_job_predictions",
    response_class=FileResponse,
    responses={
        200: {"description": "The predictions archive", "content": file_content("application/zip")},
        **_RESULT_ERRORS,
    },
)
async def get_predictions(job_id: str, jobs: JobsDep) -> FileResponse:
    record = await _succeeded_or_409(jobs, job_id)
    if not record.predictions or not Path(record.predictions).is_file():
        raise ApiError(404, "The job's predictions are no longer on the server.")
    return FileResponse(
        record.predictions, media_type="application/zip", filename=f"{job_id}-predictions.zip"
    )


@router.get(
    "/jobs/{job_id}/report",
    summary="A succeeded labelled job's evaluation report",
    description="The evaluation JSON of `rangeret evaluate`: miou, accuracy, iou by class, "
    "confusion[pred][gt]; for a panoptic job, that of `rangeret evaluate --panoptic` (its "
    "benchmark's keys) with `task`, `headline`, `precision` and `backend`.",
    response_class=FileResponse,
    responses={
        200: {
            "description": "The evaluation report",
            "content": {"application/json": {"schema": {"type": "object"}}},
        },
        **_RESULT_ERRORS,
    },
    operation_id="get_job_report",
)
async def get_report(job_id: str, jobs: JobsDep) -> FileResponse:
    record = await _succeeded_or_409(jobs, job_id)
    if not record.report:
        raise ApiError(404, "The job's scans had no labels, so it has no evaluation report.")
    if not Path(record.report).is_file():
        raise ApiError(404, "The job's report is no longer on the server.")
    return FileResponse(record.report, media_type="application/json")


@router.get(
    "/jobs/{job_id}/plots/{name}",
    summary="A succeeded labelled job's report PNG",
    description="One of the job's `plots`: IoU per class, the confusion matrix, IoU by distance "
    "band, mIoU per sequence, as `rangeret evaluate --plots` draws them.",
    operation_id="get_job_plot",
    response_class=FileResponse,
    responses={
        200: {"description": "The PNG", "content": file_content("image/png")},
        **_RESULT_ERRORS,
    },
)
async def get_plot(job_id: str, name: str, jobs: JobsDep) -> FileResponse:
    record = await _succeeded_or_409(jobs, job_id)
    path = await asyncio.to_thread(plot_path, record, name)
    if path is None:
        raise ApiError(404, f"The job has no plot {name[:64]!r}; its plots are listed in 'plots'.")
    return FileResponse(path, media_type="image/png")


@router.delete(
    "/jobs/{job_id}",
    summary="Cancel a job and remove its files",
    description="A queued or running job is cancelled and its files removed; a finished job's files and record are removed.",
    operation_id="cancel_job",
    response_model=JobStatus,
    responses=error_responses(
        400,
        403,
        404,
        503,
        507,
        described={507: "A full disk under the job database"},
    ),
)
async def cancel_job(job_id: str, gw: GatewayDep, jobs: JobsDep) -> JobStatus:
    record = await asyncio.to_thread(jobs.cancel, job_id)
    if record is None:
        raise ApiError(404, f"There is no job {job_id[:64]!r}.")
    return await asyncio.to_thread(job_status, record, gw.models.default)


async def _record_or_404(jobs: JobManager, job_id: str) -> JobRecord:
    """The stored job, read in a worker thread; 404 when there is none."""
    record = await asyncio.to_thread(jobs.store.get, job_id)
    if record is None:
        raise ApiError(404, f"There is no job {job_id[:64]!r}.")
    return record


async def _succeeded_or_409(jobs: JobManager, job_id: str) -> JobRecord:
    """The stored job; 404 when there is none, 409 until it has succeeded."""
    record = await _record_or_404(jobs, job_id)
    if record.state is not JobState.succeeded:
        raise ApiError(
            409, f"The job is {record.state.value}, and results exist only once it has succeeded."
        )
    return record


async def _archive_job(
    request: Request, gw: Gateway, intake: JobIntake, model: ModelEntry, panoptic: bool = False
) -> JobRecord:
    """Refuse an upload that cannot fit, or a `panoptic` one of a model without thing classes,
    before it is read, else receive it into a new job of `model`."""
    settings = gw.settings
    try:
        if panoptic:
            check_panoptic(model)
        await asyncio.to_thread(intake.check_upload, declared_length(request))
    except (ApiError, JobInputError) as exc:
        answer = exc if isinstance(exc, ApiError) else job_error_answer(exc)
        raise await refused_body(request, settings, answer, upload=True) from exc

    async def receive(path: Path) -> None:
        await receive_archive(request, path, settings.max_archive_bytes, settings.upload_timeout_s)

    with answered():
        return await intake.archive_job(receive, model, panoptic)


async def _dataset_request(request: Request, gw: Gateway) -> DatasetJobRequest:
    """The JSON body of a dataset job: 400 when it is not JSON or not a valid request."""
    body = await read_body(request, gw.settings.max_body_bytes, timeout=gw.settings.body_timeout_s)
    try:
        data = json.loads(body)
    except (ValueError, UnicodeDecodeError) as exc:
        raise ApiError(400, "The request body is not valid JSON.") from exc
    except RecursionError as exc:
        raise ApiError(400, "The request body's JSON is nested too deeply.") from exc
    try:
        return DatasetJobRequest.model_validate(data)
    except ValidationError as exc:
        raise ApiError(400, validation_sentence(exc.errors(), "body")) from exc
