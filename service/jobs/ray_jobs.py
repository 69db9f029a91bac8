"""Gateway jobs as Ray jobs: each one submitted through a cluster's Jobs API and followed there.

`RayJobExecutor` submits the entrypoint `ray job submit` runs, `python -m workers.predict_job`,
with the network options of the job's model, writing into the job's predictions folder (on
storage every node mounts; the nodes run the installed package). It follows the job through its progress record
in that folder (`workers.progress`) and its status in the Jobs API, and the gateway then writes
the predictions zip and the report from those files, as for a job run in-process.

- The submission id is `<job id>-<n>`, `n` counted in the job store before each submission, as
  the Jobs API refuses an id it has seen.
- A job is finished once its final progress record is written: the scans it lists as failed fail
  the gateway job, as in-process (the Ray job then ends FAILED, which alone means nothing).
- A job died when its Ray job ended without a final record, or the Jobs API no longer knows it:
  it is submitted again, and skips the scans already written, up to `MAX_SUBMISSIONS` times.
- A cancelled job's Ray job is stopped. A gateway that stops leaves its Ray jobs running; the
  next one re-attaches to the stored submission when it is still pending or running.
- A Jobs API that does not answer is a pause of up to `UNREACHABLE_S` seconds, then the job fails
  with a sentence naming the address; one that refuses the gateway fails the job at once.
"""

from __future__ import annotations

import enum
import json
import logging
import re
import shlex
import time
from pathlib import Path
from typing import TYPE_CHECKING

from rangeret.dataset.layout import ScanEntry, is_complete
from rangeret.dataset.selection import DatasetSelection
from rangeret.inference.spec import InferenceSpec
from service.jobs.executors import JobControl, JobError, Progress
from service.jobs.jobs_api import JobsApi, JobsApiError, JobsApiUnreachable
from workers.progress import JobProgress, progress_path, read_progress

if TYPE_CHECKING:
    from service.models.catalog import ModelCatalog

log = logging.getLogger(__name__)

#: Submissions of one job (the first and the re-submissions after it died) before it fails.
MAX_SUBMISSIONS = 3
#: Seconds between two looks at a job's progress record and its status in the Jobs API.
POLL_S = 1.0
#: Longest the Jobs API may go without answering before the jobs that wait on it fail.
UNREACHABLE_S = 60.0
#: Longest a cancel waits for its Ray job to end once it is asked to stop.
STOP_WAIT_S = 30.0

#: Ray job statuses of a job that has not ended.
WAITING_STATUSES = frozenset({"PENDING", "RUNNING"})
#: Ray job statuses of a job that has ended.
ENDED_STATUSES = frozenset({"SUCCEEDED", "FAILED", "STOPPED"})


class Verdict(enum.Enum):
    """Where a Ray job stands: running on, finished (final record written), or died."""

    running = "running"
    finished = "finished"
    died = "died"


def verdict(status: str | None, record: JobProgress | None) -> Verdict:
    """Decide from the Ray job's `status` (None: the Jobs API does not know the submission) and
    its progress `record`: finished once the final record is written, whatever the status (a
    job with failed scans ends FAILED); died when it ended, or is unknown, without one."""
    if record is not None and record.finished:
        return Verdict.finished
    if status is None or status in ENDED_STATUSES:
        return Verdict.died
    return Verdict.running


def submission_id(job_id: str, number: int) -> str:
    """The Ray submission id of a gateway job's `number`th submission."""
    return f"{job_id}-{number}"


#: An absolute path in a log line: a '/' that starts no word, then path characters.
_ABSOLUTE_PATH = re.compile(r"(?<![\w.:/])/[\w.@+-]+(?:/[\w.@+-]*)*")


def without_paths(text: str) -> str:
    """`text` with every absolute path cut to its last part (`…/name`), so that a reason shown to
    a client names no server folder (read roots, the Python path, job folders)."""
    return _ABSOLUTE_PATH.sub(lambda m: "…/" + m.group(0).rstrip("/").rsplit("/", 1)[-1], text)


class RayJobExecutor:
    """Runs each gateway job as a Ray job through the Jobs API at `address` (see the module).

    `models` are the gateway's models: a job's Ray job gets its model's `InferenceSpec` as the
    entrypoint's one JSON option `--inference-spec`, a checkpoint or profile file named by a
    relative path named by its absolute path, as are the job's folders, since the Ray job runs
    elsewhere; the model's profile's point record tells which predictions are already whole.
    `api`, `poll_s`, `unreachable_s` and `max_submissions` default to the module's constants.
    With `read_roots`, the Ray job reads scans only from under those folders (`--read-roots`: a
    scan that leads elsewhere when it is read is its failure).
    """

    backend = "ray-jobs"

    def __init__(
        self,
        address: str,
        models: ModelCatalog,
        *,
        api: JobsApi | None = None,
        poll_s: float = POLL_S,
        unreachable_s: float = UNREACHABLE_S,
        max_submissions: int = MAX_SUBMISSIONS,
        read_roots: list[Path] | None = None,
    ) -> None:
        self.address = address
        self.read_roots = read_roots
        self.models = models
        self.specs = {entry.name: _absolute_files(entry.spec) for entry in models}
        self.api = api or JobsApi(address)
        self.poll_s = poll_s
        self.unreachable_s = unreachable_s
        self.max_submissions = max_submissions
        self.precision: str | None = None
        self.inference_backend = models.default_entry.spec.backend

    def entrypoint(self, selection: DatasetSelection, out: Path, model: str | None = None) -> str:
        """The shell command of a job's Ray job: `python -m workers.predict_job` on the
        selection's sequences (a tables layout's whole split of its version, where the job names
        one) into `out`, with the spec of the model `model` (None: the default), which finds
        objects where the selection is for panoptic segmentation."""
        spec = self.specs[self.models.get(model).name].replace(panoptic=selection.panoptic)
        root = str(Path(selection.root).absolute())
        argv = ["python", "-m", "workers.predict_job", "--dataset", root]
        split, version = selection.split, selection.version
        argv += ["--split", split] if split else ["--sequences", *selection.sequences]
        argv += ["--version", version] if version else []
        argv += ["--out", str(Path(out).absolute())]
        argv += ["--inference-spec", json.dumps(spec.to_mapping(), sort_keys=True)]
        if self.read_roots:
            argv += ["--read-roots", *(str(Path(r).absolute()) for r in self.read_roots)]
        return shlex.join(argv)

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
        """Submit the job with its model `model` (None: the default; with `panoptic`, finding
        objects too), or re-attach to its stored submission, and follow it until its final
        record, submitting it again when it dies; failures by scan key, as in-process.

        Returns early when `cancel` is set: a cancelled job's Ray job is stopped first, one
        paused by a gateway stop is left running. `JobError` when it cannot go on.
        """
        entry = self.models.get(model)
        self.inference_backend = entry.spec.backend
        before = sum(is_complete(e, out, record=entry.profile.points) for e in entries)
        follow = _Follow(
            self, entry.name, entries, dataset, sequences, out, progress, cancel, before, panoptic
        )
        return follow.run()


def _absolute_files(spec: InferenceSpec) -> InferenceSpec:
    """`spec` with a checkpoint or profile file named by a relative path that exists here named by
    its absolute path."""
    files = {
        name: str(Path(value).absolute())
        for name in ("checkpoint", "profile")
        if (value := getattr(spec, name)) is not None
        and not Path(value).is_absolute()
        and Path(value).exists()
    }
    return spec.replace(**files)


class _Follow:
    """One `RayJobExecutor.predict` call: the submission it follows and what it has seen."""

    def __init__(
        self,
        executor: RayJobExecutor,
        model: str,
        entries: list[ScanEntry],
        dataset: Path,
        sequences: list[str],
        out: Path,
        progress: Progress,
        control: JobControl,
        before: int,
        panoptic: bool = False,
    ) -> None:
        self.executor = executor
        self.panoptic = panoptic
        self.model = model
        self.api = executor.api
        self.entries = entries
        self.dataset = dataset
        self.sequences = sequences
        self.out = out
        self.progress = progress
        self.control = control
        self.before = before
        self.reported: tuple[int, int] | None = None
        self.number = control.submission()

    @property
    def sid(self) -> str:
        """The Ray submission id of the submission followed now."""
        return submission_id(self.control.job_id, self.number)

    def run(self) -> dict[str, str]:
        """Submit or re-attach, then poll the progress record and the Ray job's status until the
        job finishes, dies past the limit, or the runner sets the control."""
        if self.number == 0:
            if not self._submit():
                return {}
        else:
            log.info("job %s: following its Ray job %s again", self.control.job_id, self.sid)
        silent_since: float | None = None
        ended_once = False
        while True:
            record = read_progress(self.out)
            if record is not None:
                self._report(record)
                if record.finished:
                    return self._finished(record)
            if self.control.is_set():
                self._leave()
                return {}
            try:
                status = self.api.status(self.sid)
            except JobsApiUnreachable as exc:
                now = time.monotonic()
                if silent_since is None:
                    silent_since = now
                    log.warning("job %s: %s; waiting for it", self.control.job_id, exc)
                elif now - silent_since > self.executor.unreachable_s:
                    raise JobError(
                        f"{exc} for {self.executor.unreachable_s:g} s while the job's Ray job "
                        f"{self.sid} ran"
                    ) from exc
                self.control.wait(self.executor.poll_s)
                continue
            except JobsApiError as exc:
                raise JobError(str(exc)) from exc
            silent_since = None
            if verdict(status, record) is Verdict.died:
                if ended_once:  # its final record was looked for after it ended, twice
                    self._died(status)
                    if not self._submit():
                        return {}
                    ended_once = False
                    continue
                ended_once = True
            else:
                ended_once = False
            self.control.wait(self.executor.poll_s)

    def _report(self, record: JobProgress) -> None:
        """Pass the record's counts on to the runner, as scans of this `predict` call."""
        pending = len(self.entries) - self.before
        written = min(max(0, record.done - self.before), pending)
        counts = (written + record.failed, record.failed)
        if counts != self.reported:
            self.reported = counts
            self.progress(counts[0], counts[1], pending)

    def _finished(self, record: JobProgress) -> dict[str, str]:
        """The outcome of a final record: its failures, or a `JobError` for bad input."""
        if record.precision:
            self.executor.precision = record.precision
        if record.error:
            raise JobError(f"{record.error} (Ray job {self.sid})")
        log.info("job %s: its Ray job %s finished", self.control.job_id, self.sid)
        return dict(record.failures)

    def _died(self, status: str | None) -> None:
        """Fail the job once its last submission died, naming it; else log the death."""
        how = (
            f"ended {status}" if status else f"is unknown to the Ray Jobs API at {self.api.address}"
        )
        if self.number >= self.executor.max_submissions:
            tail = without_paths(self.api.log_tail(self.sid)) if status else ""
            raise JobError(
                f"the job's Ray job {self.sid} {how} without finishing, after "
                f"{self.number} submissions (the limit)"
                + (f"; its log ends: {tail}" if tail else "")
            )
        log.warning(
            "job %s: its Ray job %s %s without finishing; submitting it again",
            self.control.job_id,
            self.sid,
            how,
        )

    def _submit(self) -> bool:
        """Store the next submission's number, then submit it (a stale progress record removed
        first); False when the job was cancelled or the gateway stops meanwhile."""
        self.number = self.control.next_submission()
        self.out.mkdir(
            parents=True, exist_ok=True
        )  # where the Ray job's records go, even early ones
        progress_path(self.out).unlink(missing_ok=True)
        job = self.control.record()
        selection = DatasetSelection(
            self.dataset,
            tuple(self.sequences),
            self.executor.models.get(self.model).profile.layout,
            None if job is None else job.split,
            None if job is None else job.version,
            self.panoptic,
        )
        entrypoint = self.executor.entrypoint(selection, self.out, self.model)
        metadata = {"rangeret_job": self.control.job_id}
        since: float | None = None
        while True:
            try:
                self.api.submit(self.sid, entrypoint, metadata)
                log.info("job %s: submitted as Ray job %s", self.control.job_id, self.sid)
                return True
            except JobsApiUnreachable as exc:
                if since is None:
                    since = time.monotonic()
                    log.warning("job %s: %s; trying again", self.control.job_id, exc)
                elif time.monotonic() - since > self.executor.unreachable_s:
                    raise JobError(f"the job could not be submitted: {exc}") from exc
            except JobsApiError as exc:
                if self._known():  # an earlier try that seemed to fail went through
                    return True
                raise JobError(f"the job could not be submitted: {exc}") from exc
            if self.control.wait(self.executor.poll_s):
                if self.control.cancelled and self._known():
                    self._stop()
                return False
            if self._known():
                return True

    def _known(self) -> bool:
        """Whether the Jobs API knows the current submission id (False when it does not answer)."""
        try:
            return self.api.status(self.sid) is not None
        except JobsApiError:
            return False

    def _leave(self) -> None:
        """Stop following: stop the Ray job of a cancelled job, leave it running otherwise."""
        if self.control.cancelled:
            self._stop()
        else:
            log.info(
                "job %s: the gateway stops; its Ray job %s runs on", self.control.job_id, self.sid
            )

    def _stop(self) -> None:
        """Stop the Ray job and wait (bounded) until it has ended, so that no file of the
        cancelled job appears after its folder is removed."""
        try:
            self.api.stop(self.sid)
            deadline = time.monotonic() + STOP_WAIT_S
            while time.monotonic() < deadline:
                status = self.api.status(self.sid)
                if status is None or status in ENDED_STATUSES:
                    log.info(
                        "job %s: cancelled, its Ray job %s %s",
                        self.control.job_id,
                        self.sid,
                        status,
                    )
                    return
                time.sleep(0.2)
            log.warning(
                "job %s: its Ray job %s did not stop within %g s",
                self.control.job_id,
                self.sid,
                STOP_WAIT_S,
            )
        except JobsApiError as exc:
            log.warning(
                "job %s: its Ray job %s could not be stopped: %s",
                self.control.job_id,
                self.sid,
                exc,
            )
