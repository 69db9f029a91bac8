"""Running a job's scans through the network.

A `JobExecutor` predicts a job's scans: `LocalExecutor` runs `predict_tree` in this process;
`service.jobs.ray_jobs.RayJobExecutor` submits each job to a Ray cluster through its Jobs API.
Both read the scans with the served profile's layout and point record, and skip the scans whose
prediction is already written, so an interrupted job resumes where it stopped. The runner hands
each `predict` a `JobControl`, which it sets when the job must stop running here and which tells
a cancelled job from a gateway that stops.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

from rangeret.dataset.layout import ScanEntry
from rangeret.dataset.selection import DatasetSelection
from rangeret.inference.runner import predict_tree
from service.jobs.store import JobRecord, JobStore
from service.models.pool import ModelPool, PoolFull
from service.schemas import JobState

if TYPE_CHECKING:
    from service.labelling.pooled import ModelRuntime

#: `progress(seen, failed, pending)`: of the scans a `predict` call had to predict, `seen` are
#: through and `failed` of them failed.
Progress = Callable[[int, int, int], None]


class JobError(Exception):
    """A job that cannot go on, with the one sentence that becomes its reason."""


class JobControl(threading.Event):
    """The runner's hold on one running job: set when the job must stop running here.

    Set either because the job was cancelled (`cancelled`: work it started elsewhere is stopped)
    or because the gateway stops (work that runs elsewhere goes on and is found again when the
    gateway starts). It also reads and counts the job's submissions in the store.
    """

    def __init__(self, job_id: str, store: JobStore) -> None:
        super().__init__()
        self.job_id = job_id
        self.store = store

    def record(self) -> JobRecord | None:
        """The job's stored record (None once it is forgotten)."""
        return self.store.get(self.job_id)

    @property
    def cancelled(self) -> bool:
        """Whether the job was cancelled (or forgotten), rather than paused by a gateway stop."""
        record = self.record()
        return record is None or record.state is JobState.cancelled

    def submission(self) -> int:
        """The number of the job's latest submission (0: never submitted)."""
        record = self.record()
        return record.submission if record is not None else 0

    def next_submission(self) -> int:
        """Count a new submission and return its number, stored before it is made."""
        return self.store.next_submission(self.job_id)


class JobExecutor(Protocol):
    """Runs the network over a job's scans (in this process or on a Ray cluster)."""

    backend: str
    #: The precision the network ran at in the last `predict` (None before the first).
    precision: str | None
    #: The inference backend that runs the network (torch or onnxruntime).
    inference_backend: str

    def predict(
        self,
        entries: list[ScanEntry],
        dataset: Path,
        sequences: list[str],
        out: Path,
        progress: Progress,
        cancel: JobControl,
        model: str | None = None,
        panoptic: bool = False,
    ) -> dict[str, str]:
        """Write the predictions of the scans not done yet with the served model `model` (None:
        the default), with `panoptic` the benchmark's panoptic labels of their objects; return
        failures by scan key.

        Returns early once `cancel` is set; `JobError` when the job cannot go on.
        """
        ...


class LocalExecutor:
    """`predict_tree` in this process with the job's model, taken from the gateway's pool of
    loaded models and held for the whole job (the network its single scans share, one pass at
    a time); it reads the dataset in the layout and point record of the model's profile, and,
    with `read_roots`, only scans that lie under those folders when they are read."""

    backend = "local"

    def __init__(
        self,
        pool: ModelPool[ModelRuntime],
        default: str,
        batch_size: int = 1,
        read_roots: list[Path] | None = None,
    ) -> None:
        self.pool = pool
        self.default = default
        self.batch_size = batch_size
        self.read_roots = read_roots
        self.precision: str | None = None
        self.inference_backend = "torch"

    def predict(
        self,
        entries: list[ScanEntry],
        dataset: Path,
        sequences: list[str],
        out: Path,
        progress: Progress,
        cancel: threading.Event,
        model: str | None = None,
        panoptic: bool = False,
    ) -> dict[str, str]:
        """Predict the job's scans `entries` (of the dataset's sequences) into `out` with `model`
        (None: the default; with `panoptic`, its objects clustered as the model's clustering
        options say), skipping scans already done; a cancel or a gateway stop both stop it after
        the batch in flight. `JobError` when the model cannot be loaded because running jobs
        hold every slot."""
        name = model or self.default
        try:
            runtime = self.pool.acquire(name)
        except PoolFull as exc:
            raise JobError(str(exc)) from exc
        try:
            assert runtime.predictor is not None  # a job's runtime always has its network
            predictor = runtime.predictor.with_clustering(runtime.clustering if panoptic else None)
            self.precision, self.inference_backend = predictor.precision, predictor.backend
            layout = predictor.profile.layout
            summary = predict_tree(
                predictor,
                DatasetSelection(dataset, tuple(sequences), layout, panoptic=panoptic),
                out,
                batch_size=self.batch_size,
                progress=False,
                on_progress=progress,
                cancel=cancel,
                read_roots=None if self.read_roots is None else [str(r) for r in self.read_roots],
                runner="service job",
                entries=entries,
            )
        finally:
            self.pool.release(name)
        return summary.failed
