"""/v1/jobs: start a job over whole sequences, list and follow jobs, fetch results, cancel.

A job comes from an uploaded archive (multipart field `archive`) or names a dataset under the data
roots (JSON). Both are read with the served profile: an archive's scans are its point records, a
dataset lies in its layout. The job store is only ever called through a worker thread, never on
the event loop.
"""

from __future__ import annotations

import asyncio
import errno
import json
import re
from collections.abc import Sequence
from datetime import datetime, timezone
from pathlib import Path

from fastapi import APIRouter, Request
from fastapi.responses import FileResponse, JSONResponse
from pydantic import ValidationError

from rangeret.dataset.layout import DatasetLayoutError, ScanEntry, list_scans, resolve_sequences
from service.archives import ArchiveError, ArchiveLimits, extract_archive
from service.dependencies import GatewayDep, JobsDep
from service.errors import ApiError, error_responses, validation_sentence
from service.gateway import Gateway
from service.jobs import JobManager, JobRecord, JobRefused, disk_full, expected_output_bytes
from service.jobs.manager import PLOTS_DIR
from service.paths import escaping_scans, outside_roots_sentence
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


#: A report PNG's name, as `rangeret.evaluation.plots.write_plots` names them.
_PLOT_NAME = re.compile(r"^[a-z][a-z-]{0,63}\.png$")


def report_plots(record: JobRecord) -> list[str]:
    """The names of a succeeded labelled job's report PNGs (none for other jobs)."""
    if record.state is not JobState.succeeded or not record.report:
        return []
    folder = Path(record.report).parent / PLOTS_DIR
    try:
        return sorted(p.name for p in folder.iterdir() if _PLOT_NAME.fullmatch(p.name))
    except OSError:
        return []


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
    try:
        await asyncio.to_thread(jobs.check_queue)
    except JobRefused as exc:
        await drain(request, gw.settings.max_body_bytes, timeout=gw.settings.body_timeout_s)
        raise ApiError(exc.status_code, str(exc)) from exc
    if kind == "multipart/form-data":
        record = await _archive_job(request, gw, jobs)
    elif kind == "application/json":
        record = await _dataset_job(request, gw, jobs)
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
    if name not in await asyncio.to_thread(report_plots, record):
        raise ApiError(404, f"The job has no plot {name[:64]!r}; its plots are listed in 'plots'.")
    path = Path(record.report).parent / PLOTS_DIR / name
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


async def _archive_job(request: Request, gw: Gateway, jobs: JobManager) -> JobRecord:
    """Receive, check and extract an uploaded archive into a new job's folder; queue the job."""
    settings = gw.settings
    declared = declared_length(request)
    if declared is not None:
        used = await asyncio.to_thread(jobs.disk_usage)
        if used + declared > settings.max_job_bytes:
            await drain(request, settings.max_body_bytes, timeout=settings.upload_timeout_s)
            exc = disk_full(declared, used, settings.max_job_bytes)
            raise ApiError(exc.status_code, str(exc))
    job_id, folder = await asyncio.to_thread(jobs.new_job)
    try:
        upload = folder / "upload.part"
        await receive_archive(
            request, upload, settings.max_archive_bytes, settings.upload_timeout_s
        )
        limits = ArchiveLimits(
            settings.max_archive_bytes,
            settings.max_archive_members,
            settings.max_points,
            settings.max_extracted_bytes,
        )
        try:
            found = await asyncio.to_thread(
                extract_archive,
                upload,
                folder / "data",
                limits,
                record=gw.profile.points,
                layout=gw.profile.layout,
            )
        except ArchiveError as exc:
            raise ApiError(exc.status_code, str(exc)) from exc
        finally:
            upload.unlink(missing_ok=True)
        entries = await asyncio.to_thread(
            list_scans, found.root, found.sequences, layout=gw.profile.layout
        )
        return await _submit(jobs, job_id, "archive", found.root, found.sequences, entries, gw)
    except OSError as exc:
        await asyncio.to_thread(jobs.remove_files, job_id)
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            raise ApiError(
                507,
                f"Insufficient storage: the disk of the jobs folder {jobs.jobs_dir} is full; "
                "free space there, or upload a smaller archive.",
            ) from exc
        raise
    except BaseException:
        await asyncio.to_thread(jobs.remove_files, job_id)
        raise


async def _dataset_job(request: Request, gw: Gateway, jobs: JobManager) -> JobRecord:
    """Check a dataset job request (profile, roots, sequences in the profile's layout) and queue
    the job."""
    body = await read_body(request, gw.settings.max_body_bytes, timeout=gw.settings.body_timeout_s)
    try:
        data = json.loads(body)
    except (ValueError, UnicodeDecodeError) as exc:
        raise ApiError(400, "The request body is not valid JSON.") from exc
    except RecursionError as exc:
        raise ApiError(400, "The request body's JSON is nested too deeply.") from exc
    try:
        job = DatasetJobRequest.model_validate(data)
    except ValidationError as exc:
        raise ApiError(400, validation_sentence(exc.errors(), "body")) from exc
    profile = gw.profile
    if job.profile is not None and job.profile != profile.name:
        raise ApiError(
            400,
            f"The request is for the {job.profile[:64]!r} profile but this gateway serves the "
            f"{profile.name!r} profile: one gateway serves one network.",
        )
    roots = gw.settings.data_roots
    root = resolve_dataset(job.dataset, roots)
    try:
        sequences = resolve_sequences(job.split, job.sequences, profile.labels, profile.layout)
        entries = await asyncio.to_thread(list_scans, root, sequences, layout=profile.layout)
    except (DatasetLayoutError, ValueError) as exc:
        raise ApiError(400, f"The dataset cannot be used: {str(exc)[:400]}") from exc
    escaping = await asyncio.to_thread(escaping_scans, entries, roots)
    if escaping:
        raise ApiError(403, outside_roots_sentence(escaping))
    job_id, _ = await asyncio.to_thread(jobs.new_job)
    try:
        return await _submit(jobs, job_id, "dataset", root, sequences, entries, gw)
    except BaseException:
        await asyncio.to_thread(jobs.remove_files, job_id)
        raise


async def _submit(
    jobs: JobManager,
    job_id: str,
    kind: str,
    root: Path,
    sequences: list[str],
    entries: list[ScanEntry],
    gw: Gateway,
) -> JobRecord:
    """Queue a job whose folder is ready, with the output its scans are expected to write; 429
    or 507 when the gateway cannot take it now."""
    expected = await asyncio.to_thread(expected_output_bytes, entries, gw.profile.points)
    try:
        return await asyncio.to_thread(jobs.submit, job_id, kind, root, sequences, expected)
    except JobRefused as exc:
        raise ApiError(exc.status_code, str(exc)) from exc
