"""The `Gateway`: what every endpoint uses (settings, the served dataset profile, worker pool,
single-scan admission, batcher, job manager, metrics).

`create_app` builds one per app and keeps it in `app.state.gateway`; the app's lifespan starts it
(job store, runner, batcher) and stops it. Routes get it through `service.dependencies`.
"""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass, field
from typing import Protocol

from rangeret.profiles import DatasetProfile
from service.admission import ScanAdmission
from service.batching import ScanBackend, ScanBatcher
from service.errors import ApiError
from service.jobs import JobExecutor, JobManager, JobStore
from service.metrics import GatewayMetrics
from service.page_assets import PageFiles, PageNotBuilt
from service.settings import Settings

log = logging.getLogger(__name__)


class WorkerPool(ScanBackend, Protocol):
    """What the gateway needs from `workers.pool.ScanPool` / `LocalScanPool`."""

    backend: str

    def health(self) -> dict:
        """The workers' state."""
        ...


@dataclass
class Gateway:
    """Everything the endpoints use, built by `create_app` and started by its lifespan.

    One gateway serves one network, so one `profile`: its point record, labels, layout and splits.
    """

    settings: Settings
    pool: WorkerPool
    executor: JobExecutor
    profile: DatasetProfile
    checkpoint_sha256: str | None
    dispatchers: int
    #: The served network's name (None: taken from the workers' descriptions).
    model: str | None = None
    metrics: GatewayMetrics = field(init=False)
    admission: ScanAdmission = field(init=False)
    batcher: ScanBatcher | None = None
    jobs: JobManager | None = None
    #: The web page's files (`service.page_assets`), read on first use.
    page: PageFiles = field(default_factory=PageFiles)

    def __post_init__(self) -> None:
        self.metrics = GatewayMetrics(self.profile.name)
        self.admission = ScanAdmission(
            self.settings.max_queued_scans, self.settings.max_queued_bytes
        )

    async def start(self) -> None:
        """Open the job store, recover and start the runner, start the batcher."""
        settings = self.settings
        settings.jobs_folder.mkdir(parents=True, exist_ok=True)
        store = await asyncio.to_thread(JobStore, settings.database_path)
        self.jobs = JobManager(
            store,
            self.executor,
            settings.jobs_folder,
            settings.retention.total_seconds(),
            profile=self.profile,
            checkpoint_sha256=self.checkpoint_sha256,
            on_scans=self.metrics.job_scans,
            max_running=settings.max_running_jobs,
            max_queued=settings.max_queued_jobs,
            max_bytes=settings.max_job_bytes,
            read_roots=settings.data_roots,
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
        try:
            await asyncio.to_thread(self.page.get)
        except PageNotBuilt as exc:
            log.warning("%s Until then / answers 503; the API is served.", exc)

    async def stop(self) -> None:
        """Stop the batcher and the job runner (a running job resumes at the next start)."""
        if self.batcher is not None:
            await self.batcher.stop()
        if self.jobs is not None:
            await asyncio.to_thread(self.jobs.stop)
            await asyncio.to_thread(self.jobs.store.close)

    def manager(self) -> JobManager:
        """The job manager (the app is started)."""
        if self.jobs is None:
            raise ApiError(503, "The gateway is starting; try again in a moment.")
        return self.jobs
