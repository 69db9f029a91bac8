"""A prediction job's progress record in its output folder, written by the job and read by others.

`python -m workers.predict_job` keeps `<out>/progress.json` (`JobProgress`): a record when it
starts, one after batches (at most about once a second, `ProgressWriter`) and a final one at the
very end, also when scans failed or the job stopped on bad input. Whoever submitted the job (the
gateway) follows it there: the final record says the job is over and how it ended, and a job whose
process ended without one died. Every record is written atomically, so a reader never sees half of
one; a missing or unreadable record reads as None.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path

from rangeret.dataset.fields import is_int
from rangeret.io.atomic import atomic_write_text

#: The record's name in the job's output folder.
PROGRESS_FILE = "progress.json"
#: Shortest time between two records written after batches; the final record is always written.
PROGRESS_INTERVAL_S = 1.0


@dataclass
class JobProgress:
    """Where a prediction job stands.

    `done` counts the scans with a prediction (those written by earlier runs included), `failed`
    those that could not be predicted, named with the reason in `failures` (in the final record).
    `finished` marks the final record; `error` is the one sentence of a job stopped on bad input;
    `precision` is the one the network ran at (None when no batch ran).
    """

    total: int = 0
    done: int = 0
    failed: int = 0
    failures: dict[str, str] = field(default_factory=dict)
    finished: bool = False
    error: str | None = None
    precision: str | None = None

    def to_json(self) -> str:
        """The record as the file holds it."""
        return json.dumps(asdict(self), indent=1, sort_keys=True) + "\n"

    @classmethod
    def from_json(cls, text: str) -> JobProgress:
        """The record in `text`; `ValueError` when it is not one."""
        data = json.loads(text)
        if not isinstance(data, dict):
            raise ValueError("a progress record is a JSON object")
        counts = {name: data.get(name, 0) for name in ("total", "done", "failed")}
        if not all(is_int(v) and v >= 0 for v in counts.values()):
            raise ValueError(f"bad counts in a progress record: {counts}")
        failures = data.get("failures", {})
        if not isinstance(failures, dict) or not all(
            isinstance(k, str) and isinstance(v, str) for k, v in failures.items()
        ):
            raise ValueError("a progress record's failures map scan keys to reasons")
        finished = data.get("finished", False)
        error, precision = data.get("error"), data.get("precision")
        if not isinstance(finished, bool) or not all(
            v is None or isinstance(v, str) for v in (error, precision)
        ):
            raise ValueError("bad finished, error or precision in a progress record")
        return cls(**counts, failures=failures, finished=finished, error=error, precision=precision)


def progress_path(out: Path | str) -> Path:
    """Where the job writing predictions into `out` keeps its progress record."""
    return Path(out) / PROGRESS_FILE


def write_progress(out: Path | str, progress: JobProgress) -> None:
    """Replace the progress record of the job writing into `out`, atomically."""
    atomic_write_text(progress_path(out), progress.to_json())


def read_progress(out: Path | str) -> JobProgress | None:
    """The progress record of the job writing into `out`; None when there is none or it cannot be
    read (a record is replaced whole, so the next read sees a complete one)."""
    try:
        return JobProgress.from_json(progress_path(out).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError, TypeError):
        return None


class ProgressWriter:
    """Writes a job's records: `start`, `batch` after each batch (at most one record per
    `interval` seconds, and always the one that counts every scan), then `finish` once."""

    def __init__(
        self,
        out: Path | str,
        interval: float = PROGRESS_INTERVAL_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.out = Path(out)
        self.interval = interval
        self.clock = clock
        self.progress = JobProgress()
        self._skipped = 0
        self._pending = 0
        self._last: float | None = None

    @property
    def finished(self) -> bool:
        """Whether the final record is written."""
        return self.progress.finished

    def start(self, total: int, done: int) -> None:
        """The first record: `total` scans, `done` of them predicted by earlier runs."""
        self._skipped, self._pending = done, total - done
        self.progress = JobProgress(total=total, done=done)
        self._write()

    def batch(self, seen: int, failed: int, _pending: int = 0) -> None:
        """After a batch: `seen` of this run's scans are through, `failed` of them failed (the
        signature of `run_pipeline`'s progress callback)."""
        self.progress.done = self._skipped + seen - failed
        self.progress.failed = failed
        last = seen >= self._pending
        if last or self._last is None or self.clock() - self._last >= self.interval:
            self._write()

    def finish(
        self,
        failures: Mapping[str, str] | None = None,
        error: str | None = None,
        precision: str | None = None,
    ) -> None:
        """The final record: the failed scans by key, or the sentence of the error that stopped
        the job, and the precision the network ran at."""
        failures = dict(failures or {})
        self.progress.failures = failures
        self.progress.failed = max(self.progress.failed, len(failures))
        self.progress.error = " ".join(error.split()) if error else None
        self.progress.precision = precision
        self.progress.finished = True
        self._write()

    def _write(self) -> None:
        write_progress(self.out, self.progress)
        self._last = self.clock()


#: Scans a run completes after its first before `TimeLeft` estimates anything.
MIN_SCANS_FOR_ESTIMATE = 3
#: Seconds a run goes on after its first scan before `TimeLeft` estimates anything.
MIN_SECONDS_FOR_ESTIMATE = 5.0


class TimeLeft:
    """Seconds a run of `total` scans has left, from its rate since its first scan came through.

    The first scan carries the start-up (actors, weights, the first batch's compilation), so the
    rate is measured from it on, and there is no estimate (None) until `min_scans` more scans
    came through over at least `min_seconds`: an early estimate is mostly start-up and far off.
    """

    def __init__(
        self,
        total: int,
        min_scans: int = MIN_SCANS_FOR_ESTIMATE,
        min_seconds: float = MIN_SECONDS_FOR_ESTIMATE,
        clock: Callable[[], float] = time.perf_counter,
    ) -> None:
        self.total = total
        self.min_scans = min_scans
        self.min_seconds = min_seconds
        self.clock = clock
        self._first: tuple[int, float] | None = None

    def update(self, done: int) -> float | None:
        """The estimate once `done` scans are through; 0 once all are, None while it would
        mean nothing."""
        now = self.clock()
        if done >= self.total:
            return 0.0
        if self._first is None:
            if done > 0:
                self._first = (done, now)
            return None
        since, started = self._first
        scans, seconds = done - since, now - started
        if scans < self.min_scans or seconds < self.min_seconds:
            return None
        return (self.total - done) * seconds / scans
