"""/v1/jobs: start a job over whole sequences, list and follow jobs, fetch results, cancel.

A job comes from an uploaded archive (multipart field `archive`) or names a dataset under the data
roots (JSON). The routes parse the request and reply; `service.jobs.intake` prepares, checks and
queues a new job, and `service.jobs.results` names a job's result files. The job store is only
ever called through a worker thread, never on the event loop.
"""

from __future__ import annotations

import asyncio
import json
from datetime import datetime, timezone
from pathlib import Path

from fastapi import APIRouter, Request
from fastapi.responses import FileResponse, JSONResponse
from pydantic import ValidationError

from service.dependencies import GatewayDep, JobsDep
from service.errors import ApiError, error_responses, validation_sentence
from service.gateway import Gateway
from service.jobs import JobManager, JobRecord
from service.jobs.intake import JobIntake
from service.jobs.results import plot_path, report_plots
from service.schemas import (
    BINARY_CONTENT,
    DatasetJobRequest,
    JobCreated,
    JobList,
    JobMetrics,
    JobState,
    JobStatus,
)
from service.uploads import declared_length, drain, media_type, read_body, receive_archive

router = APIRouter(prefix="/v1")

_JOB_BODY = {
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
                        "(the served profile's point records) and optional "
                        "sequences/XX/labels/*.label, whatever the profile",
                    }
                },
                "required": ["archive"],
            }
        },
        "application/json": {"schema": DatasetJobRequest.model_json_schema()},
    },
}


def _iso(ts: float | None) -> datetime | None:
    return datetime.fromtimestamp(ts, tz=timezone.utc) if ts is not None else None


def job_status(record: JobRecord) -> JobStatus:
    """The API form of a stored job (it lists the job's plots: call it in a worker thread)."""
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
        plots=report_plots(record),
    )


@router.post(
    "/jobs",
    summary="Start a job over sequences",
    description=(
        "Either upload an archive (multipart field `archive`) laid out as sequences/XX/velodyne/*.bin "
        "with optional sequences/XX/labels/*.label (for every profile; the scans hold the served "
        "profile's point records), or name a dataset in the served profile's layout under the "
        "configured data roots in JSON. The job predicts every scan; with labels it also evaluates "
        "them."
    ),
    status_code=202,
    response_model=JobCreated,
    responses=error_responses(400, 403, 404, 408, 413, 415, 429, 507),
    openapi_extra={"requestBody": _JOB_BODY},
)
async def create_job(request: Request, gw: GatewayDep, jobs: JobsDep) -> JSONResponse:
    kind = media_type(request)
    intake = JobIntake(jobs, gw.settings, gw.profile)
    try:
        await asyncio.to_thread(intake.check_queue)
    except ApiError:
        await drain(request, gw.settings.max_body_bytes, timeout=gw.settings.body_timeout_s)
        raise
    if kind == "multipart/form-data":
        record = await _archive_job(request, gw, intake)
    elif kind == "application/json":
        record = await intake.dataset_job(await _dataset_request(request, gw))
    else:
        await drain(request, gw.settings.max_body_bytes, timeout=gw.settings.body_timeout_s)
        raise ApiError(
            415,
            "Send a job as multipart/form-data (an 'archive' file) or as application/json (a dataset).",
        )
    created = JobCreated(id=record.id, status_url=f"/v1/jobs/{record.id}")
    return JSONResponse(
        created.model_dump(), status_code=202, headers={"Location": created.status_url}
    )


@router.get("/jobs", summary="List jobs", response_model=JobList)
async def list_jobs(jobs: JobsDep) -> JobList:
    records = await asyncio.to_thread(jobs.store.list)
    return JobList(jobs=await asyncio.to_thread(lambda: [job_status(r) for r in records]))


@router.get(
    "/jobs/{job_id}",
    summary="A job's state and progress",
    response_model=JobStatus,
    responses=error_responses(404),
)
async def get_job(job_id: str, jobs: JobsDep) -> JobStatus:
    return await asyncio.to_thread(job_status, await _record_or_404(jobs, job_id))


@router.get(
    "/jobs/{job_id}/predictions",
    summary="A succeeded job's predictions (zip)",
    description="A zip of sequences/XX/predictions/*.label with directory entries for the job's sequences.",
    response_class=FileResponse,
    responses={
        200: {
            "description": "The predictions archive",
            "content": {"application/zip": BINARY_CONTENT},
        },
        **error_responses(404, 409),
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
    description="The evaluation JSON of `rangeret evaluate`: miou, accuracy, iou by class, confusion[pred][gt].",
    response_class=FileResponse,
    responses={
        200: {
            "description": "The evaluation report",
            "content": {"application/json": {"schema": {"type": "object"}}},
        },
        **error_responses(404, 409),
    },
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
    response_class=FileResponse,
    responses={
        200: {"description": "The PNG", "content": {"image/png": BINARY_CONTENT}},
        **error_responses(404, 409),
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
    response_model=JobStatus,
    responses=error_responses(404),
)
async def delete_job(job_id: str, jobs: JobsDep) -> JobStatus:
    record = await asyncio.to_thread(jobs.cancel, job_id)
    if record is None:
        raise ApiError(404, f"There is no job {job_id[:64]!r}.")
    return await asyncio.to_thread(job_status, record)


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


async def _archive_job(request: Request, gw: Gateway, intake: JobIntake) -> JobRecord:
    """Refuse an upload that cannot fit before it is read, else receive it into a new job."""
    settings = gw.settings
    try:
        await asyncio.to_thread(intake.check_upload, declared_length(request))
    except ApiError:
        await drain(request, settings.max_body_bytes, timeout=settings.upload_timeout_s)
        raise

    async def receive(path: Path) -> None:
        await receive_archive(request, path, settings.max_archive_bytes, settings.upload_timeout_s)

    return await intake.archive_job(receive)


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
