"""The job scheduler: queue, runner threads, admission, cancellation, recovery and retention.

Up to `max_running` jobs run at once, each on its own runner thread, and the oldest queued job
always starts next, so no job waits behind a long one for a free runner for ever. A job is
admitted only while fewer than `max_queued` jobs wait and its expected output fits in the disk
the job folders may use (`service.jobs.capacity`); its folder records the profile it was accepted
for. A runner hands each claimed job to `service.jobs.work.JobWork`, which predicts, zips,
evaluates and stores the final record; the scheduler records the failures it raises and queues a
job the gateway's stop interrupted again. A restarted gateway queues a job that was running
again, and it resumes (finished predictions are skipped), or marks it failed with the reason when
it cannot. Finished jobs' files and records are removed after the retention time.
"""

from __future__ import annotations

import logging
import re
import shutil
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path

from rangeret.dataset.selection import DatasetSelection
from service.jobs.capacity import disk_full, disk_short, folder_bytes, queue_full
from service.jobs.executors import JobControl, JobError, JobExecutor
from service.jobs.reasons import failure_sentence
from service.jobs.store import JobDatabaseFull, JobRecord, JobStore
from service.jobs.work import PROFILE_FILE, JobWork
from service.models.catalog import ModelCatalog
from service.schemas import JobState

log = logging.getLogger(__name__)

#: A job interrupted this many times by a gateway that was killed (a clean stop does not count)
#: is failed rather than resumed again.
MAX_ATTEMPTS = 3
#: The same for a job submitted to a Ray cluster, which a gateway restart does not interrupt
#: (the next gateway follows it again), so only a gateway that keeps failing while it finishes
#: the job (zip, report) stops it.
MAX_FOLLOWS = 10
#: The file the gateway puts in every job folder it makes: the proof that it may delete it.
MARKER_FILE = ".rangeret-job"
#: How often a failure the job database refused (a full disk) is tried again.
UNRECORDED_RETRY_S = 2.0
#: The name of a job folder: the job's id, 32 lowercase hex digits.
JOB_ID = re.compile(r"[0-9a-f]{32}")


class JobManager:
    """Admits, runs (up to `max_running` at once, oldest first), cancels, resumes and expires
    jobs.

    `read_roots`, when given, are the folders a dataset job may read (links resolved); the jobs
    folder, where uploaded archives are extracted, is always allowed then.
    """

    def __init__(
        self,
        store: JobStore,
        executor: JobExecutor,
        jobs_dir: Path,
        retention_s: float,
        *,
        models: ModelCatalog,
        on_scans: Callable[[int, str], None] | None = None,
        max_running: int = 1,
        max_queued: int | None = None,
        max_bytes: int | None = None,
        read_roots: Sequence[Path] | None = None,
    ) -> None:
        if max_running < 1:
            raise ValueError("max_running must be at least 1")
        self.store = store
        self.jobs_dir = jobs_dir
        self.retention_s = retention_s
        self.models = models
        self.max_running = max_running
        self.max_queued = max_queued
        self.max_bytes = max_bytes
        self.work = JobWork(
            store,
            executor,
            models,
            read_roots=None
            if read_roots is None
            else [Path(r).resolve() for r in read_roots] + [jobs_dir.resolve()],
            on_scans=on_scans,
        )
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._running: dict[str, JobControl] = {}
        self._running_lock = threading.Lock()
        self._admit_lock = threading.Lock()
        #: Bytes each queued or running job is expected to write (see `capacity`).
        self._expected: dict[str, int] = {}
        #: Sizes of finished jobs' folders, which no longer change.
        self._finished_sizes: dict[str, int] = {}
        self._threads: list[threading.Thread] = []
        #: Failures the job database refused to record (a full disk), by job id.
        self._unrecorded: dict[str, str] = {}
        #: Wakes the sweeper early: to retry those failures, or to stop.
        self._sweep_wake = threading.Event()

    # Folders ------------------------------------------------------------------------------

    def job_dir(self, job_id: str) -> Path:
        """The folder of a job's files."""
        return self.jobs_dir / job_id

    def new_job(self) -> tuple[str, Path]:
        """A fresh job id and its new folder, marked as the gateway's own (`MARKER_FILE`)."""
        job_id = uuid.uuid4().hex
        folder = self.job_dir(job_id)
        folder.mkdir(parents=True)
        (folder / MARKER_FILE).write_text(job_id + "\n")
        return job_id, folder

    def owns(self, folder: Path) -> bool:
        """Whether `folder` is one the gateway made: a job id's name and the marker naming it."""
        if not (JOB_ID.fullmatch(folder.name) and folder.is_dir() and not folder.is_symlink()):
            return False
        try:
            return (folder / MARKER_FILE).read_text().strip() == folder.name
        except OSError:
            return False

    def remove_files(self, job_id: str) -> None:
        """Delete a job's folder."""
        shutil.rmtree(self.job_dir(job_id), ignore_errors=True)

    # Life cycle -----------------------------------------------------------------------------

    def check_queue(self) -> None:
        """`QueueFull` when the queue is full, so an upload is refused before it is read."""
        if self.max_queued is not None and self.store.count(JobState.queued) >= self.max_queued:
            raise queue_full(self.max_queued)

    def disk_usage(self) -> int:
        """Bytes the job folders hold or expect: each folder's files, and for queued and running
        jobs at least what they are expected to write."""
        total = 0
        if not self.jobs_dir.is_dir():
            return 0
        finished = {j.id for j in self.store.list() if j.state.finished}
        for folder in self.jobs_dir.iterdir():
            job_id = folder.name
            if job_id in finished:
                if job_id not in self._finished_sizes:
                    self._finished_sizes[job_id] = folder_bytes(folder)
                total += self._finished_sizes[job_id]
            else:
                total += max(folder_bytes(folder), self._expected.get(job_id, 0))
        return total

    def submit(
        self,
        job_id: str,
        kind: str,
        selection: DatasetSelection,
        expected_bytes: int = 0,
        model: str | None = None,
    ) -> JobRecord:
        """Queue a job over the `selection` of the served model `model` (None: the default)
        whose folder is ready (a panoptic one where the selection is for panoptic segmentation),
        noting the profile it is accepted for, and wake a runner;
        `QueueFull` when the queue is full, `NoRoom` when its `expected_bytes` of output do not
        fit in the disk the jobs may use."""
        entry = self.models.entries[model or self.models.default]
        with self._admit_lock:
            self.check_queue()
            if self.max_bytes is not None:
                used = self.disk_usage()
                if used + expected_bytes > self.max_bytes:
                    raise disk_full(expected_bytes, used, self.max_bytes)
            free = shutil.disk_usage(self.jobs_dir).free
            if expected_bytes > free:
                raise disk_short(expected_bytes, free, self.jobs_dir)
            (self.job_dir(job_id) / PROFILE_FILE).write_text(entry.profile.name + "\n")
            record = self.store.create(
                job_id,
                kind,
                selection.root,
                selection.sequences,
                entry.name,
                version=selection.version,
                split=selection.split,
                panoptic=selection.panoptic,
            )
            self._expected[job_id] = expected_bytes
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
            with self._running_lock:
                running = self._running.get(job_id)
            if running is not None:
                running.set()  # the runner removes the files once the batch in flight is done
            else:
                self.remove_files(job_id)
                self._expected.pop(job_id, None)
            return self.store.get(job_id)
        self.remove_files(job_id)
        self.store.delete(job_id)
        self._finished_sizes.pop(job_id, None)
        return record

    def start(self) -> None:
        """Recover from the previous run, then start the runners and the retention sweeper."""
        self.recover()
        self._stop.clear()
        self._threads = [
            threading.Thread(target=self._run_loop, name=f"rangeret-jobs-{i}", daemon=True)
            for i in range(self.max_running)
        ]
        self._threads.append(
            threading.Thread(target=self._sweep_loop, name="rangeret-retention", daemon=True)
        )
        for thread in self._threads:
            thread.start()

    def stop(self, timeout: float = 30.0) -> None:
        """Stop after the batches in flight; running jobs are queued again and resume at the next
        start (a job on a Ray cluster runs on there, and is followed again)."""
        self._stop.set()
        self._wake.set()
        self._sweep_wake.set()
        with self._running_lock:
            for cancel in self._running.values():
                cancel.set()
        for thread in self._threads:
            thread.join(timeout)
        self._threads = []

    def recover(self) -> None:
        """Requeue jobs a stopped gateway left running (or fail them, with the reason); tidy folders."""
        for job in self.store.list(JobState.running):
            if job.attempts >= (MAX_FOLLOWS if job.submission else MAX_ATTEMPTS):
                self.store.finish(
                    job.id,
                    JobState.failed,
                    reason=f"the gateway was killed {job.attempts} times while this job ran (clean "
                    "stops do not count), so it is not resumed again",
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
        foreign: list[str] = []
        if self.jobs_dir.is_dir():
            for entry in sorted(self.jobs_dir.iterdir()):
                if entry.name in known:
                    continue
                if self.owns(entry):
                    log.info("removing %s: no job owns it (an upload cut short)", entry)
                    shutil.rmtree(entry, ignore_errors=True)
                else:
                    foreign.append(entry.name)
        if foreign:
            shown = ", ".join(foreign[:10]) + (
                f" and {len(foreign) - 10} more" if len(foreign) > 10 else ""
            )
            log.warning(
                "the jobs folder %s holds %d entr%s the gateway did not make (%s): left alone; "
                "give the gateway a folder of its own (RANGERET_JOBS_DIR)",
                self.jobs_dir,
                len(foreign),
                "y" if len(foreign) == 1 else "ies",
                shown,
            )

    def sweep(self, now: float | None = None) -> int:
        """Remove the files and records of jobs finished longer than the retention time ago."""
        now = time.time() if now is None else now
        expired = self.store.finished_before(now - self.retention_s)
        for job in expired:
            self.remove_files(job.id)
            self.store.delete(job.id)
            self._finished_sizes.pop(job.id, None)
        if expired:
            log.info("removed %d finished job(s) past the retention time", len(expired))
        return len(expired)

    # Threads ------------------------------------------------------------------------------

    def _sweep_loop(self) -> None:
        interval = min(60.0, max(0.5, self.retention_s / 4))
        swept = time.monotonic()
        while not self._stop.is_set():
            self._sweep_wake.wait(
                min(interval, UNRECORDED_RETRY_S) if self._unrecorded else interval
            )
            self._sweep_wake.clear()
            if self._stop.is_set():
                return
            self._record_unrecorded()
            if time.monotonic() - swept < interval:
                continue
            swept = time.monotonic()
            try:
                self.sweep()
            except Exception:
                log.exception("the retention sweep failed")

    def _fail(self, job_id: str, reason: str) -> None:
        """Mark a job failed; when the job database takes no writes (a full disk), keep the
        reason and write it as soon as it does (`_record_unrecorded`)."""
        try:
            self.store.finish(job_id, JobState.failed, reason=reason)
        except JobDatabaseFull as exc:
            log.warning(
                "job %s failed (%s) and %s; recorded once it takes writes", job_id, reason, exc
            )
            self._unrecorded[job_id] = reason
            self._sweep_wake.set()

    def _record_unrecorded(self) -> None:
        """Write the failures the job database refused, now that it may take them."""
        for job_id, reason in list(self._unrecorded.items()):
            try:
                self.store.finish(job_id, JobState.failed, reason=reason)
            except JobDatabaseFull:
                return
            self._unrecorded.pop(job_id, None)
            log.info("job %s is recorded as failed: %s", job_id, reason)

    def _run_loop(self) -> None:
        while not self._stop.is_set():
            job = self.store.claim_next()
            if job is None:
                self._wake.wait(1.0)
                self._wake.clear()
                continue
            try:
                self._run(job)
            except Exception:
                log.exception("job %s failed in the runner", job.id)

    def _run(self, job: JobRecord) -> None:
        """Run one claimed job to a final state (or back to queued when the gateway stops)."""
        cancel = JobControl(job.id, self.store)
        with self._running_lock:
            self._running[job.id] = cancel
        try:
            finished = self.work.run(job, self.job_dir(job.id), cancel)
            if not finished and self._stop.is_set() and self.store.requeue(job.id, graceful=True):
                log.info(
                    "job %s paused by the gateway stopping; it resumes at the next start", job.id
                )
        except JobError as exc:
            log.warning("job %s failed: %s", job.id, exc)
            self._fail(job.id, failure_sentence(exc, self.job_dir(job.id)))
        except JobDatabaseFull as exc:
            log.warning("job %s stopped: %s", job.id, exc)
            self._fail(job.id, failure_sentence(exc, self.job_dir(job.id)))
        except Exception as exc:
            log.exception("job %s failed", job.id)
            self._fail(job.id, failure_sentence(exc, self.job_dir(job.id)))
        finally:
            with self._running_lock:
                self._running.pop(job.id, None)
        latest = self.store.get(job.id)
        if latest is None or latest.state is not JobState.queued:
            self._expected.pop(job.id, None)
        if latest is not None and latest.state is JobState.cancelled:
            self.remove_files(job.id)
