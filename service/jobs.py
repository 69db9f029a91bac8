"""Jobs over whole sequences: records in SQLite, one background runner, results and retention.

A job predicts every scan of its sequences into `JOBS/<id>/predictions` (the Ray pipeline when a
cluster is configured, `predict_tree` in this process otherwise), then writes the predictions zip
and, for sequences with ground truth, the evaluation report. Its state, progress and errors live
in SQLite, so a restarted gateway knows every job: a job that was running is queued again and
resumes (finished predictions are skipped), or is marked failed with the reason when it cannot.
Finished jobs' files and records are removed after the retention time.
"""

from __future__ import annotations

import json
import logging
import shutil
import sqlite3
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

from rangeret.atomic import atomic_path
from rangeret.evaluation import evaluate_predictions
from rangeret.inference import Predictor, PredictorSpec
from rangeret.labels import LabelConfig, semantickitti
from rangeret.layout import ScanEntry, discover, prediction_path
from rangeret.predict import is_complete, list_scans, predict_tree
from rangeret.projection import ProjectionConfig
from rangeret.submission import TEST_SEQUENCES, required_directories
from rangeret.zipfiles import ReproducibleZip
from service.schemas import JobState

log = logging.getLogger(__name__)

#: A job interrupted this many times by gateway restarts is failed rather than resumed again.
MAX_ATTEMPTS = 3
#: Failed scans kept in a job's record (the count is always exact).
MAX_ERRORS = 1000
PREDICTIONS_ZIP = "predictions.zip"
REPORT_JSON = "report.json"

Progress = Callable[[int, int, int], None]


@dataclass
class JobRecord:
    """One job as stored: what it runs on, where it is, and what it produced."""

    id: str
    kind: str
    state: JobState
    dataset: str
    sequences: list[str]
    created: float
    total: int = 0
    done: int = 0
    failed: int = 0
    errors: list[str] = field(default_factory=list)
    reason: str | None = None
    metrics: dict | None = None
    predictions: str | None = None
    report: str | None = None
    started: float | None = None
    finished: float | None = None
    attempts: int = 0


_COLUMNS = (
    "id", "kind", "state", "dataset", "sequences", "created", "total", "done", "failed", "errors",
    "reason", "metrics", "predictions", "report", "started", "finished", "attempts",
)  # fmt: skip


class JobStore:
    """Job records in one SQLite file, safe to use from the event loop and the runner thread."""

    def __init__(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path
        self._lock = threading.Lock()
        self._db = sqlite3.connect(path, check_same_thread=False, isolation_level=None, timeout=30)
        with self._lock:
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=NORMAL")
            self._db.execute(
                """CREATE TABLE IF NOT EXISTS jobs (
                    id TEXT PRIMARY KEY, kind TEXT NOT NULL, state TEXT NOT NULL,
                    dataset TEXT NOT NULL, sequences TEXT NOT NULL, created REAL NOT NULL,
                    total INTEGER NOT NULL DEFAULT 0, done INTEGER NOT NULL DEFAULT 0,
                    failed INTEGER NOT NULL DEFAULT 0, errors TEXT NOT NULL DEFAULT '[]',
                    reason TEXT, metrics TEXT, predictions TEXT, report TEXT,
                    started REAL, finished REAL, attempts INTEGER NOT NULL DEFAULT 0)"""
            )
            self._db.execute("CREATE INDEX IF NOT EXISTS jobs_state ON jobs (state, created)")

    def close(self) -> None:
        """Close the database."""
        with self._lock:
            self._db.close()

    def _execute(self, sql: str, params: Sequence = ()) -> int:
        """Run one statement; the number of rows it changed."""
        with self._lock:
            return self._db.execute(sql, params).rowcount

    def _query(self, sql: str, params: Sequence = ()) -> list[JobRecord]:
        with self._lock:
            rows = self._db.execute(
                f"SELECT {', '.join(_COLUMNS)} FROM jobs {sql}", params
            ).fetchall()
        return [_record(row) for row in rows]

    def create(self, job_id: str, kind: str, dataset: Path, sequences: Sequence[str]) -> JobRecord:
        """Store a new queued job."""
        now = time.time()
        self._execute(
            "INSERT INTO jobs (id, kind, state, dataset, sequences, created) VALUES (?, ?, ?, ?, ?, ?)",
            (job_id, kind, JobState.queued.value, str(dataset), json.dumps(list(sequences)), now),
        )
        return JobRecord(job_id, kind, JobState.queued, str(dataset), list(sequences), now)

    def get(self, job_id: str) -> JobRecord | None:
        """The job with this id, or None."""
        found = self._query("WHERE id = ?", (job_id,))
        return found[0] if found else None

    def list(self, *states: JobState) -> list[JobRecord]:
        """Jobs, newest first; only those in `states` when given."""
        if not states:
            return self._query("ORDER BY created DESC")
        marks = ", ".join("?" * len(states))
        return self._query(
            f"WHERE state IN ({marks}) ORDER BY created DESC", [s.value for s in states]
        )

    def next_queued(self) -> JobRecord | None:
        """The oldest queued job."""
        found = self._query("WHERE state = ? ORDER BY created LIMIT 1", (JobState.queued.value,))
        return found[0] if found else None

    def counts(self) -> dict[str, int]:
        """Number of jobs in each state."""
        with self._lock:
            rows = self._db.execute("SELECT state, COUNT(*) FROM jobs GROUP BY state").fetchall()
        found = dict(rows)
        return {s.value: int(found.get(s.value, 0)) for s in JobState}

    def start(self, job_id: str) -> bool:
        """queued -> running; False when the job is no longer queued."""
        return (
            self._execute(
                "UPDATE jobs SET state = ?, started = ?, attempts = attempts + 1 WHERE id = ? AND state = ?",
                (JobState.running.value, time.time(), job_id, JobState.queued.value),
            )
            == 1
        )

    def progress(self, job_id: str, total: int, done: int, failed: int) -> None:
        """Record a running job's counts."""
        self._execute(
            "UPDATE jobs SET total = ?, done = ?, failed = ? WHERE id = ? AND state = ?",
            (total, done, failed, job_id, JobState.running.value),
        )

    def finish(
        self,
        job_id: str,
        state: JobState,
        reason: str | None = None,
        errors: Sequence[str] = (),
        metrics: dict | None = None,
        predictions: Path | None = None,
        report: Path | None = None,
    ) -> bool:
        """running -> a final state; False when the job was cancelled meanwhile."""
        return (
            self._execute(
                """UPDATE jobs SET state = ?, reason = ?, errors = ?, metrics = ?, predictions = ?,
               report = ?, finished = ? WHERE id = ? AND state = ?""",
                (
                    state.value,
                    reason,
                    json.dumps(list(errors)[:MAX_ERRORS]),
                    json.dumps(metrics) if metrics is not None else None,
                    str(predictions) if predictions else None,
                    str(report) if report else None,
                    time.time(),
                    job_id,
                    JobState.running.value,
                ),
            )
            == 1
        )

    def requeue(self, job_id: str) -> bool:
        """running -> queued, to be resumed."""
        return (
            self._execute(
                "UPDATE jobs SET state = ? WHERE id = ? AND state = ?",
                (JobState.queued.value, job_id, JobState.running.value),
            )
            == 1
        )

    def cancel(self, job_id: str) -> bool:
        """queued or running -> cancelled; False when the job had already finished."""
        return (
            self._execute(
                "UPDATE jobs SET state = ?, reason = ?, finished = ? WHERE id = ? AND state IN (?, ?)",
                (
                    JobState.cancelled.value,
                    "cancelled by request",
                    time.time(),
                    job_id,
                    JobState.queued.value,
                    JobState.running.value,
                ),
            )
            == 1
        )

    def delete(self, job_id: str) -> None:
        """Forget a job."""
        self._execute("DELETE FROM jobs WHERE id = ?", (job_id,))

    def finished_before(self, when: float) -> list[JobRecord]:
        """Finished jobs whose end is older than `when` (unix time)."""
        states = [JobState.succeeded.value, JobState.failed.value, JobState.cancelled.value]
        return self._query("WHERE state IN (?, ?, ?) AND finished < ?", [*states, when])


def _record(row: Sequence) -> JobRecord:
    values = dict(zip(_COLUMNS, row, strict=True))
    values["state"] = JobState(values["state"])
    values["sequences"] = json.loads(values["sequences"])
    values["errors"] = json.loads(values["errors"])
    values["metrics"] = json.loads(values["metrics"]) if values["metrics"] else None
    return JobRecord(**values)


class JobExecutor(Protocol):
    """Runs the network over a job's scans (in this process or on a Ray cluster)."""

    backend: str

    def predict(
        self,
        entries: list[ScanEntry],
        dataset: Path,
        sequences: list[str],
        out: Path,
        progress: Progress,
        cancel: threading.Event,
    ) -> dict[str, str]:
        """Write the predictions of the scans not done yet; return failures by scan key."""
        ...


class LocalExecutor:
    """`predict_tree` in this process, with its own predictor (built on first use)."""

    backend = "local"

    def __init__(self, spec: PredictorSpec, batch_size: int = 1) -> None:
        self.spec = spec
        self.batch_size = batch_size
        self._predictor: Predictor | None = None

    def predict(
        self,
        entries: list[ScanEntry],
        dataset: Path,
        sequences: list[str],
        out: Path,
        progress: Progress,
        cancel: threading.Event,
    ) -> dict[str, str]:
        """Predict the dataset's sequences into `out`, skipping scans already done."""
        if self._predictor is None:
            self._predictor = self.spec.build()
        summary = predict_tree(
            self._predictor,
            dataset,
            sequences,
            out,
            batch_size=self.batch_size,
            progress=False,
            on_progress=progress,
            cancel=cancel,
        )
        return summary.failed


class RayExecutor:
    """`workers.pipeline.run_pipeline` on the connected Ray cluster."""

    backend = "ray"

    def __init__(
        self,
        spec: PredictorSpec,
        projection: ProjectionConfig,
        batch_size: int = 1,
        actors: int | None = None,
        label_config: LabelConfig | None = None,
    ) -> None:
        self.spec = spec
        self.projection = projection
        self.batch_size = batch_size
        self.actors = actors
        self.label_config = label_config

    def predict(
        self,
        entries: list[ScanEntry],
        dataset: Path,
        sequences: list[str],
        out: Path,
        progress: Progress,
        cancel: threading.Event,
    ) -> dict[str, str]:
        """Send the scans without a finished prediction through the pipeline."""
        from workers.pipeline import PipelineOptions, run_pipeline

        pending = [e for e in entries if not is_complete(e, out)]
        options = PipelineOptions(batch_size=self.batch_size, actors=self.actors)
        result = run_pipeline(
            self.spec,
            self.projection,
            pending,
            out,
            options,
            self.label_config,
            progress=progress,
            cancel=cancel,
        )
        return result.failed


def labelled_sequences(dataset: Path, sequences: Sequence[str]) -> list[str]:
    """The sequences every scan of which has a ground-truth label file."""
    found = discover(dataset, sequences, missing_ok=True).by_sequence()
    return [s for s, scans in found.items() if scans and all(e.label_path for e in scans)]


def write_predictions_zip(
    pred_root: Path,
    entries: Sequence[ScanEntry],
    sequences: Sequence[str],
    path: Path,
    description: str,
) -> None:
    """The job's predictions as a reproducible zip with explicit directory entries.

    When all its sequences are test sequences, the archive holds the directory entries of every
    test sequence, as the benchmark server wants, so it passes the submission validator.
    """
    names = list(dict.fromkeys(sequences))
    if all(s in TEST_SEQUENCES for s in names):
        directories = list(required_directories())
    else:
        directories = ["sequences/"]
        for seq in sorted(names):
            directories += [f"sequences/{seq}/", f"sequences/{seq}/predictions/"]
    with atomic_path(path) as tmp, ReproducibleZip(tmp) as zf:
        for name in directories:
            zf.add_directory(name)
        for entry in entries:
            name = f"sequences/{entry.sequence}/predictions/{entry.name}.label"
            zf.add_file(name, prediction_path(pred_root, entry.sequence, entry.name).read_bytes())
        zf.add_file("description.txt", description.rstrip("\n") + "\n")


class JobManager:
    """Creates, runs (one at a time, oldest first), cancels, resumes and expires jobs."""

    def __init__(
        self,
        store: JobStore,
        executor: JobExecutor,
        jobs_dir: Path,
        retention_s: float,
        label_config: LabelConfig | None = None,
        checkpoint_sha256: str | None = None,
        on_scans: Callable[[int], None] | None = None,
    ) -> None:
        self.store = store
        self.executor = executor
        self.jobs_dir = jobs_dir
        self.retention_s = retention_s
        self.label_config = label_config or semantickitti()
        self.checkpoint_sha256 = checkpoint_sha256
        self.on_scans = on_scans
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._current: tuple[str, threading.Event] | None = None
        self._current_lock = threading.Lock()
        self._threads: list[threading.Thread] = []

    # Folders ------------------------------------------------------------------------------

    def job_dir(self, job_id: str) -> Path:
        """The folder of a job's files."""
        return self.jobs_dir / job_id

    def new_job(self) -> tuple[str, Path]:
        """A fresh job id and its (new, empty) folder."""
        job_id = uuid.uuid4().hex
        folder = self.job_dir(job_id)
        folder.mkdir(parents=True)
        return job_id, folder

    def remove_files(self, job_id: str) -> None:
        """Delete a job's folder."""
        shutil.rmtree(self.job_dir(job_id), ignore_errors=True)

    # Life cycle -----------------------------------------------------------------------------

    def submit(self, job_id: str, kind: str, dataset: Path, sequences: Sequence[str]) -> JobRecord:
        """Queue a job whose folder is ready and wake the runner."""
        record = self.store.create(job_id, kind, dataset, sequences)
        self._wake.set()
        return record

    def cancel(self, job_id: str) -> JobRecord | None:
        """Cancel a queued or running job and remove its files; a finished job is forgotten.

        Returns the job's last record, or None when there is no such job.
        """
        record = self.store.get(job_id)
        if record is None:
            return None
        if self.store.cancel(job_id):
            with self._current_lock:
                current = self._current
            if current is not None and current[0] == job_id:
                current[1].set()  # the runner removes the files once the batch in flight is done
            else:
                self.remove_files(job_id)
            return self.store.get(job_id)
        self.remove_files(job_id)
        self.store.delete(job_id)
        return record

    def start(self) -> None:
        """Recover from the previous run, then start the runner and the retention sweeper."""
        self.recover()
        self._stop.clear()
        self._threads = [
            threading.Thread(target=self._run_loop, name="rangeret-jobs", daemon=True),
            threading.Thread(target=self._sweep_loop, name="rangeret-retention", daemon=True),
        ]
        for thread in self._threads:
            thread.start()

    def stop(self, timeout: float = 30.0) -> None:
        """Stop after the batch in flight; a running job is queued again and resumes at next start."""
        self._stop.set()
        self._wake.set()
        with self._current_lock:
            if self._current is not None:
                self._current[1].set()
        for thread in self._threads:
            thread.join(timeout)
        self._threads = []

    def recover(self) -> None:
        """Requeue jobs a stopped gateway left running (or fail them, with the reason); tidy folders."""
        for job in self.store.list(JobState.running):
            if job.attempts >= MAX_ATTEMPTS:
                self.store.finish(
                    job.id,
                    JobState.failed,
                    reason=f"the gateway stopped {job.attempts} times while this job ran, so it is not resumed again",
                )
            elif not Path(job.dataset).is_dir():
                self.store.finish(
                    job.id,
                    JobState.failed,
                    reason=f"the gateway restarted and the job's input {job.dataset} no longer exists",
                )
            else:
                self.store.requeue(job.id)
                log.info("job %s was running when the gateway stopped; it resumes", job.id)
        for job in self.store.list(JobState.cancelled):
            self.remove_files(job.id)
        known = {job.id for job in self.store.list()}
        if self.jobs_dir.is_dir():
            for folder in self.jobs_dir.iterdir():
                if folder.is_dir() and folder.name not in known:
                    log.info("removing %s: no job owns it (an upload cut short)", folder)
                    shutil.rmtree(folder, ignore_errors=True)

    def sweep(self, now: float | None = None) -> int:
        """Remove the files and records of jobs finished longer than the retention time ago."""
        now = time.time() if now is None else now
        expired = self.store.finished_before(now - self.retention_s)
        for job in expired:
            self.remove_files(job.id)
            self.store.delete(job.id)
        if expired:
            log.info("removed %d finished job(s) past the retention time", len(expired))
        return len(expired)

    # Threads ------------------------------------------------------------------------------

    def _sweep_loop(self) -> None:
        interval = min(60.0, max(0.5, self.retention_s / 4))
        while not self._stop.wait(interval):
            try:
                self.sweep()
            except Exception:
                log.exception("the retention sweep failed")

    def _run_loop(self) -> None:
        while not self._stop.is_set():
            job = self.store.next_queued()
            if job is None:
                self._wake.wait(1.0)
                self._wake.clear()
                continue
            try:
                self._run(job)
            except Exception:
                log.exception("job %s failed in the runner", job.id)

    def _run(self, job: JobRecord) -> None:
        """Run one job to a final state (or back to queued when the gateway stops)."""
        cancel = threading.Event()
        with self._current_lock:
            self._current = (job.id, cancel)
        try:
            if self.store.start(job.id):
                try:
                    self._execute(job, cancel)
                except Exception as exc:
                    log.exception("job %s failed", job.id)
                    self.store.finish(job.id, JobState.failed, reason=_sentence(exc))
        finally:
            with self._current_lock:
                self._current = None
        latest = self.store.get(job.id)
        if latest is not None and latest.state is JobState.cancelled:
            self.remove_files(job.id)

    def _execute(self, job: JobRecord, cancel: threading.Event) -> None:
        dataset = Path(job.dataset)
        folder = self.job_dir(job.id)
        out = folder / "predictions"
        entries = list_scans(dataset, job.sequences)
        skipped = sum(is_complete(e, out) for e in entries)
        self.store.progress(job.id, len(entries), skipped, 0)
        counted = [0]

        def progress(seen: int, failed: int, _pending: int) -> None:
            written = seen - failed
            self.store.progress(job.id, len(entries), skipped + written, failed)
            if self.on_scans is not None and written > counted[0]:
                self.on_scans(written - counted[0])
                counted[0] = written

        failures = self.executor.predict(entries, dataset, job.sequences, out, progress, cancel)
        if cancel.is_set():
            if self._stop.is_set() and self.store.requeue(job.id):
                log.info(
                    "job %s paused by the gateway stopping; it resumes at the next start", job.id
                )
            return
        if failures:
            self.store.finish(
                job.id,
                JobState.failed,
                reason=f"{len(failures)} of {len(entries)} scans could not be predicted (see errors)",
                errors=[f"{key}: {reason}" for key, reason in failures.items()],
            )
            return
        self.store.progress(job.id, len(entries), len(entries), 0)
        zip_path = folder / PREDICTIONS_ZIP
        write_predictions_zip(out, entries, job.sequences, zip_path, self._description())
        metrics = report_path = None
        labelled = labelled_sequences(dataset, job.sequences)
        if labelled:
            report = evaluate_predictions(
                dataset,
                out,
                labelled,
                config=self.label_config,
                checkpoint_sha256=self.checkpoint_sha256,
            )
            report_path = folder / REPORT_JSON
            report.write_json(report_path)
            metrics = {
                "miou": report.miou,
                "accuracy": report.accuracy,
                "iou": report.iou_by_name(),
            }
        self.store.finish(
            job.id, JobState.succeeded, metrics=metrics, predictions=zip_path, report=report_path
        )

    def _description(self) -> str:
        return (
            "RangeRet predictions written by the rangeret gateway\n"
            f"checkpoint sha256: {self.checkpoint_sha256 or 'unknown'}\n"
        )


def _sentence(exc: BaseException) -> str:
    """One readable line for an exception."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text[:500]
