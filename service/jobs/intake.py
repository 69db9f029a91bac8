"""A new job's intake: its folder prepared from an uploaded archive or a dataset on the server,
checked, and queued.

An archive job is refused before its upload is read when the queue is full or its declared
length does not fit in the disk the job folders may use; the upload is received into a new
job folder, checked and extracted there (`service.archives.extraction`) by the rules its model's profile's
layout gives, and the folder is removed again whatever stops it on the way. A dataset job names a
folder under the data roots (`OutsideDataRoots`, `NoSuchDataset`) in its model's profile, with a
split of that profile and, for a tables layout, a version (`service.jobs.selection`), and its
scans must stay under the roots once links are resolved. A panoptic job (objects too) reads the
panoptic ground truth and writes panoptic predictions; its model's profile must name thing
classes. Either is queued with the output its
scans are expected to write (`service.jobs.capacity`). Every refusal is one of
`service.jobs.errors` (an `ArchiveError` for an archive its rules refuse), a sentence the routes
answer with its status; the blocking steps run in worker threads, never on the event loop.
"""

from __future__ import annotations

import asyncio
import errno
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from rangeret.dataset.layout import DatasetLayoutError, ScanEntry
from rangeret.dataset.selection import DatasetSelection, select_dataset
from service.archives.extraction import ArchiveLimits, extract_with
from service.jobs.capacity import disk_full, expected_output_bytes
from service.jobs.errors import (
    BadJobRequest,
    NoRoom,
    NoSuchDataset,
    OutsideDataRoots,
)
from service.jobs.manager import JobManager
from service.jobs.selection import check_selection, dataset_version, incomplete_split
from service.jobs.store import JobRecord
from service.labelling.panoptic import panoptic_refusal
from service.models.catalog import ModelCatalog, ModelEntry
from service.paths import escaping_scans, outside_roots_sentence
from service.schemas import DatasetJobRequest
from service.settings import Settings

#: The file in a new job's folder an upload is received into (removed once it is extracted).
UPLOAD_FILE = "upload.part"
#: The folder in a job's folder an uploaded archive is extracted into.
DATA_DIR = "data"


@dataclass(frozen=True)
class JobInput:
    """A job's input: the dataset selection (root, sequences, a tables layout's version and the
    split its predictions go to) and its scans."""

    selection: DatasetSelection
    entries: list[ScanEntry]

    @property
    def root(self) -> Path:
        return self.selection.root

    @property
    def sequences(self) -> list[str]:
        return list(self.selection.sequences)

    @property
    def version(self) -> str | None:
        return self.selection.version

    @property
    def split(self) -> str | None:
        return self.selection.split


def check_panoptic(model: ModelEntry) -> None:
    """`BadJobRequest` when a panoptic job is asked of a model whose profile names no thing
    classes."""
    refusal = panoptic_refusal(model.profile, model.name)
    if refusal is not None:
        raise BadJobRequest(refusal)


def resolve_dataset(text: str, roots: Sequence[Path]) -> Path:
    """The dataset folder named by a job request: `OutsideDataRoots` outside the data roots,
    `NoSuchDataset` when absent."""
    if not roots:
        raise OutsideDataRoots(
            "No data roots are configured (RANGERET_DATA_ROOTS), so no dataset on the server can be used.",
        )
    try:
        path = Path(text)
        candidates = [path] if path.is_absolute() else [root / path for root in roots]
        inside = [c.resolve() for c in candidates]
    except (ValueError, OSError) as exc:
        raise BadJobRequest(f"The dataset path is not a usable path ({exc}).") from exc
    inside = [p for p in inside if any(p.is_relative_to(root) for root in roots)]
    if not inside:
        raise OutsideDataRoots("The dataset path is outside the configured data roots.")
    for candidate in inside:
        if candidate.is_dir():
            return candidate
    raise NoSuchDataset("There is no dataset folder at that path under the data roots.")


class JobIntake:
    """Prepares, checks and queues new jobs for `jobs`, under the gateway's `settings`, each in
    the profile of its model among `models`."""

    def __init__(self, jobs: JobManager, settings: Settings, models: ModelCatalog) -> None:
        self.jobs = jobs
        self.settings = settings
        self.models = models

    # Checks before a body is read ---------------------------------------------------------

    def check_queue(self) -> None:
        """`QueueFull` when the queue is full, so a job is refused before its body is read."""
        self.jobs.check_queue()

    def check_upload(self, declared: int | None) -> None:
        """`NoRoom` when an upload's `declared` length (None: not declared) does not fit beside what
        the job folders hold or expect (RANGERET_MAX_JOB_BYTES)."""
        if declared is None:
            return
        limit = self.settings.max_job_bytes
        used = self.jobs.disk_usage()
        if used + declared > limit:
            raise disk_full(declared, used, limit)

    # Archive jobs ---------------------------------------------------------------------------

    def archive_limits(self) -> ArchiveLimits:
        """What one uploaded archive may hold, from the settings."""
        settings = self.settings
        return ArchiveLimits(
            settings.max_archive_bytes,
            settings.max_archive_members,
            settings.max_points,
            settings.max_extracted_bytes,
        )

    def extract_upload(
        self, upload: Path, folder: Path, model: ModelEntry, panoptic: bool = False
    ) -> JobInput:
        """Check and extract the archive at `upload` into the job `folder` in the model's profile
        (an `ArchiveError` when it is not one the gateway takes), removing the upload; its input
        (for a `panoptic` job, with the panoptic ground truth and prediction paths)."""
        profile = model.profile
        try:
            rules = profile.layout.upload_rules(profile.points)
            found = extract_with(upload, folder / DATA_DIR, self.archive_limits(), rules)
        finally:
            upload.unlink(missing_ok=True)
        selection = DatasetSelection(
            found.root,
            tuple(found.sequences),
            profile.layout,
            version=found.version,
            panoptic=panoptic,
        )
        return JobInput(selection, selection.scans())

    async def archive_job(
        self,
        receive: Callable[[Path], Awaitable[object]],
        model: ModelEntry,
        panoptic: bool = False,
    ) -> JobRecord:
        """A new job of `model` from an upload (a `panoptic` one: objects too): `receive(path)`
        writes the upload into the new job's folder, which is then extracted and queued; the
        folder is removed when any step fails, and a full disk is `NoRoom` naming the jobs
        folder."""
        if panoptic:
            check_panoptic(model)
        jobs = self.jobs
        job_id, folder = await asyncio.to_thread(jobs.new_job)
        try:
            upload = folder / UPLOAD_FILE
            await receive(upload)
            found = await asyncio.to_thread(self.extract_upload, upload, folder, model, panoptic)
            return await self.submit(job_id, "archive", found, model)
        except OSError as exc:
            await asyncio.to_thread(jobs.remove_files, job_id)
            if exc.errno in (errno.ENOSPC, errno.EDQUOT):
                raise NoRoom(
                    f"Insufficient storage: the disk of the jobs folder {jobs.jobs_dir} is full; "
                    "free space there, or upload a smaller archive.",
                ) from exc
            raise
        except BaseException:
            await asyncio.to_thread(jobs.remove_files, job_id)
            raise

    # Dataset jobs ---------------------------------------------------------------------------

    def dataset_input(self, request: DatasetJobRequest, model: ModelEntry) -> JobInput:
        """The input a dataset job request names, in its model's profile and under the data
        roots: `BadJobRequest` for another profile, a split or version the profile or dataset does
        not have or a dataset that cannot be used, `OutsideDataRoots` outside the roots (links
        resolved), `NoSuchDataset` when absent."""
        profile = model.profile
        if request.profile is not None and request.profile != profile.name:
            raise BadJobRequest(
                f"The request is for the {request.profile[:64]!r} profile but the model "
                f"{model.name} runs with the {profile.name!r} profile.",
            )
        check_selection(request, model)
        if request.panoptic:
            check_panoptic(model)
        roots = self.settings.data_roots
        root = resolve_dataset(request.dataset, roots)
        version = dataset_version(root, request.version, model)
        try:
            selection = select_dataset(
                root,
                layout=profile.layout,
                labels=profile.labels,
                split=request.split,
                sequences=request.sequences,
                version=version,
            ).for_task(request.panoptic)
            if request.split is not None:
                missing = selection.missing()
                if missing:
                    raise BadJobRequest(
                        incomplete_split(request.split, selection.sequences, missing)
                    )
            entries = selection.scans()
        except (DatasetLayoutError, ValueError) as exc:
            raise BadJobRequest(f"The dataset cannot be used: {str(exc)[:400]}") from exc
        escaping = escaping_scans(entries, roots)
        if escaping:
            raise OutsideDataRoots(outside_roots_sentence(escaping))
        return JobInput(selection, entries)

    async def dataset_job(self, request: DatasetJobRequest) -> JobRecord:
        """A new job over the dataset `request` names with its model, checked and queued (404
        for a model the gateway does not serve)."""
        model = self.models.get(request.model)
        found = await asyncio.to_thread(self.dataset_input, request, model)
        job_id, _ = await asyncio.to_thread(self.jobs.new_job)
        try:
            return await self.submit(job_id, "dataset", found, model)
        except BaseException:
            await asyncio.to_thread(self.jobs.remove_files, job_id)
            raise

    # Both -----------------------------------------------------------------------------------

    async def submit(self, job_id: str, kind: str, found: JobInput, model: ModelEntry) -> JobRecord:
        """Queue a job of `model` whose folder is ready, with the output its scans are expected
        to write; `JobRefused` when the gateway cannot take it now."""
        jobs = self.jobs
        expected = await asyncio.to_thread(
            expected_output_bytes, found.entries, model.profile.points
        )
        return await asyncio.to_thread(
            jobs.submit, job_id, kind, found.selection, expected, model.name
        )
