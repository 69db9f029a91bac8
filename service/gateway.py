"""The `Gateway`: what every endpoint uses (settings, the served dataset profile, the single-scan
labeller and its admission, the job manager, metrics).

`create_app` builds one per app and keeps it in `app.state.gateway`; the app's lifespan starts it
(job store, runner, labeller) and stops it. Routes get it through `service.http.dependencies`.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

from rangeret.dataset.profiles import DatasetProfile
from rangeret.models.weights.demo import demo_warning, is_demo_checkpoint
from service.http.errors import ApiError
from service.http.metrics import GatewayMetrics
from service.jobs import JobExecutor, JobManager, JobStore
from service.labelling.admission import ScanAdmission
from service.models.catalog import ModelCatalog
from service.page_assets import PageFiles, PageNotBuilt
from service.settings import Settings

if TYPE_CHECKING:
    import numpy as np

    from rangeret.inference.results import ScanPrediction

log = logging.getLogger(__name__)


class ScanLabeller(Protocol):
    """What labels single scans: `service.labelling.pooled.PooledLabeller` (the loaded models in
    this process) or `service.labelling.serve_client.ServeLabeller` (the Serve application)."""

    backend: str

    async def start(self, on_batch: Callable[[int, float], None] | None = None) -> None:
        """Start serving (on the app's event loop)."""
        ...

    async def stop(self) -> None:
        """Stop; requests still waiting fail."""
        ...

    async def label_points(
        self,
        points: np.ndarray,
        knn: bool = True,
        confidence: bool = False,
        panoptic: bool = False,
        *,
        model: str,
    ) -> ScanPrediction:
        """One scan labelled by the model `model`: its points, in that model's point record;
        with `panoptic`, its panoptic labels and its objects (`instances`)."""
        ...

    def depth(self) -> int:
        """Scans accepted and not answered yet."""
        ...

    async def health(self) -> dict:
        """`{"backend", "ok", "workers": [descriptions], "error"}` for /healthz."""
        ...

    def loaded(self) -> list[str] | None:
        """The models whose networks are loaded in this process now; None where the networks
        are another process's (the Serve application's)."""
        ...


@dataclass
class Gateway:
    """Everything the endpoints use, built by `create_app` and started by its lifespan.

    A gateway serves the models of its catalog, each with its own profile (point record, labels,
    layout and splits); a request names one or gets the default.
    """

    settings: Settings
    labeller: ScanLabeller
    executor: JobExecutor
    models: ModelCatalog
    metrics: GatewayMetrics = field(init=False)
    admission: ScanAdmission = field(init=False)
    started: bool = False
    jobs: JobManager | None = None
    #: The web page's files (`service.page_assets`), read on first use.
    page: PageFiles = field(default_factory=PageFiles)

    @property
    def profile(self) -> DatasetProfile:
        """The default model's profile: that of a request or job that names no model (each job
        runs with its own model's), the one `/healthz` and the gateway's info metric report."""
        return self.models.default_entry.profile

    @property
    def checkpoint_sha256(self) -> str | None:
        """The default model's checkpoint SHA-256."""
        return self.models.default_entry.checkpoint_sha256

    def loaded_models(self) -> list[str] | None:
        """The models whose networks are loaded in this process now; None where the labeller
        keeps no pool (the Serve application holds them)."""
        return self.labeller.loaded()

    def __post_init__(self) -> None:
        self.metrics = GatewayMetrics(
            self.profile.name, {m.name: m.profile.name for m in self.models}
        )
        self.admission = ScanAdmission(
            self.settings.max_queued_scans, self.settings.max_queued_bytes
        )

    async def start(self) -> None:
        """Open the job store, recover and start the runner, start the labeller."""
        settings = self.settings
        settings.jobs_folder.mkdir(parents=True, exist_ok=True)
        store = await asyncio.to_thread(JobStore, settings.database_path)
        self.jobs = JobManager(
            store,
            self.executor,
            settings.jobs_folder,
            settings.retention.total_seconds(),
            models=self.models,
            on_scans=self.metrics.job_scans,
            max_running=settings.max_running_jobs,
            max_queued=settings.max_queued_jobs,
            max_bytes=settings.max_job_bytes,
            read_roots=settings.data_roots,
        )
        await asyncio.to_thread(self.jobs.start)
        await self.labeller.start(self.metrics.observe_batch)
        self.started = True
        self._warn_demo_weights()
        try:
            await asyncio.to_thread(self.page.get)
        except PageNotBuilt as exc:
            log.warning("%s Until then / answers 503; the API is served.", exc)

    def _warn_demo_weights(self) -> None:
        """Log, once per model, that it serves the bundled demo weights where its checkpoint was
        named (a models file, `--checkpoint`); the loader already says so when none was."""
        for entry in self.models:
            if entry.spec.checkpoint is not None and is_demo_checkpoint(entry.checkpoint_sha256):
                log.warning("model %s is %s", entry.name, demo_warning(entry.profile.name))

    async def stop(self) -> None:
        """Stop the labeller and the job runner (a running job resumes at the next start)."""
        if self.started:
            self.started = False
            await self.labeller.stop()
        if self.jobs is not None:
            await asyncio.to_thread(self.jobs.stop)
            await asyncio.to_thread(self.jobs.store.close)

    def manager(self) -> JobManager:
        """The job manager (the app is started)."""
        if self.jobs is None:
            raise ApiError(503, "The gateway is starting; try again in a moment.")
        return self.jobs
