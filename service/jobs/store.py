"""The job records in SQLite: `JobRecord`, `JobStore` and the schema version of its file.

Every job's state, progress, errors and results live in one SQLite file, so a restarted gateway
knows every job. The file's schema version is kept in `PRAGMA user_version`: a new file is
created at `SCHEMA_VERSION`, an older file is migrated to it when opened (a file from before the
version was kept has the tables of version 1), and a file of a newer version is refused.

Versions: 1, the jobs table; 2, its `submission` column (the number of the job's latest
submission to a Ray cluster, stored before the job is submitted); 3, its `model` column (the
served model the job runs with; NULL in older rows, which ran with the gateway's one model and
are the default model's); 4, its `version` and `split` columns (a tables layout's version and the
split its predictions go to; NULL in older rows, which were all of folder layouts); 5, its
`panoptic` column (1 for a job that finds objects too; 0 in older rows, which did not).
"""

from __future__ import annotations

import json
import os
import sqlite3
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from rangeret.dataset.layout import DatasetLayout
from rangeret.dataset.selection import DatasetSelection
from service.schemas import JobState

#: Failed scans kept in a job's record (the count is always exact).
MAX_ERRORS = 1000
#: The schema this code reads and writes, stored in the database's `PRAGMA user_version`.
SCHEMA_VERSION = 5

#: The statements that take a file from the version before each one to that version.
_MIGRATIONS: dict[int, tuple[str, ...]] = {
    1: (
        """CREATE TABLE IF NOT EXISTS jobs (
            id TEXT PRIMARY KEY, kind TEXT NOT NULL, state TEXT NOT NULL,
            dataset TEXT NOT NULL, sequences TEXT NOT NULL, created REAL NOT NULL,
            total INTEGER NOT NULL DEFAULT 0, done INTEGER NOT NULL DEFAULT 0,
            failed INTEGER NOT NULL DEFAULT 0, errors TEXT NOT NULL DEFAULT '[]',
            reason TEXT, metrics TEXT, predictions TEXT, report TEXT,
            started REAL, finished REAL, attempts INTEGER NOT NULL DEFAULT 0)""",
        "CREATE INDEX IF NOT EXISTS jobs_state ON jobs (state, created)",
    ),
    2: ("ALTER TABLE jobs ADD COLUMN submission INTEGER NOT NULL DEFAULT 0",),
    3: ("ALTER TABLE jobs ADD COLUMN model TEXT",),
    4: ("ALTER TABLE jobs ADD COLUMN version TEXT", "ALTER TABLE jobs ADD COLUMN split TEXT"),
    5: ("ALTER TABLE jobs ADD COLUMN panoptic INTEGER NOT NULL DEFAULT 0",),
}


class JobDatabaseError(ValueError):
    """The job database, or the folder it lives in, cannot be used; the message names the file
    and the problem in one sentence."""


class JobDatabaseFull(JobDatabaseError):
    """A write to the job database failed for want of disk space: 507 to requests, and the job
    that was writing is failed as soon as the database takes writes again."""

    def __init__(self, path: Path) -> None:
        super().__init__(
            f"the job database {path} is on a full disk: free space there, or set "
            "RANGERET_DATABASE to another disk"
        )
        self.path = path


class JobDatabaseVersionError(JobDatabaseError):
    """The job database was written by a newer gateway, with a schema this code does not know."""

    def __init__(self, path: Path, found: int) -> None:
        super().__init__(
            f"the job database {path} has schema version {found}, newer than version "
            f"{SCHEMA_VERSION} that this gateway knows: run a newer gateway, or set "
            "RANGERET_DATABASE to another file"
        )
        self.path = path
        self.found = found


def check_job_database(path: Path) -> None:
    """Raise `JobDatabaseError` when the database at `path` cannot be used: a newer schema than
    this code's (`JobDatabaseVersionError`), something else than a file in its place, a folder
    that cannot be made, or a file that is not an intact SQLite database.

    Lets the gateway refuse it in one sentence before it loads weights; a missing file passes
    when its folder can be made. Checking creates nothing.
    """
    if path.exists() and not path.is_file():
        raise JobDatabaseError(f"the job database {path} is not a file: set RANGERET_DATABASE")
    if not path.is_file():
        folder = path.parent
        while not folder.exists() and folder != folder.parent:
            folder = folder.parent
        if not folder.is_dir() or not os.access(folder, os.W_OK | os.X_OK):
            raise JobDatabaseError(
                f"the job database {path} cannot be made: {folder} is not a folder this gateway "
                "may write"
            )
        return
    try:
        db = sqlite3.connect(path, timeout=30)
        try:
            _check_version(db, path)
            problems = [row[0] for row in db.execute("PRAGMA quick_check(5)").fetchall()]
        finally:
            db.close()
    except sqlite3.DatabaseError as exc:
        raise JobDatabaseError(
            f"the job database {path} cannot be read ({exc}): move the file away, or set "
            "RANGERET_DATABASE to another one"
        ) from exc
    if problems != ["ok"]:
        raise JobDatabaseError(
            f"the job database {path} is damaged ({' '.join('; '.join(problems).split())[:200]}): "
            "move the file away, or set RANGERET_DATABASE to another one"
        )


def _check_version(db: sqlite3.Connection, path: Path) -> int:
    """The database's schema version; `JobDatabaseVersionError` when it is newer than ours."""
    found = db.execute("PRAGMA user_version").fetchone()[0]
    if found > SCHEMA_VERSION:
        raise JobDatabaseVersionError(path, found)
    return found


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
    #: The number of the job's latest submission to a Ray cluster (0: never submitted).
    submission: int = 0
    #: The served model the job runs with (None: the default, as for jobs from before models).
    model: str | None = None
    #: A tables layout's version (None: the one its dataset holds, or a folder layout).
    version: str | None = None
    #: The split a tables layout's predictions go to (None: each scene's own, or a folder layout).
    split: str | None = None
    #: Whether the job finds objects too: panoptic predictions, archive and report.
    panoptic: bool = False

    def selection(self, layout: DatasetLayout) -> DatasetSelection:
        """What the job reads of its dataset, in its profile's `layout` (its panoptic ground
        truth and prediction paths for a panoptic job)."""
        return DatasetSelection(
            Path(self.dataset),
            tuple(self.sequences),
            layout,
            self.split,
            self.version,
            self.panoptic,
        )


#: queued -> running: the first start's time is kept when a job resumes.
_START = (
    "UPDATE jobs SET state = ?, started = COALESCE(started, ?), attempts = attempts + 1 "
    "WHERE id = ? AND state = ?"
)

_COLUMNS = (
    "id", "kind", "state", "dataset", "sequences", "created", "total", "done", "failed", "errors",
    "reason", "metrics", "predictions", "report", "started", "finished", "attempts",
    "submission", "model", "version", "split", "panoptic",
)  # fmt: skip


class JobStore:
    """Job records in one SQLite file, safe to share between threads.

    The gateway calls it from worker threads and the runner thread, never on its event loop.
    """

    def __init__(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path
        self._lock = threading.Lock()
        self._db = sqlite3.connect(path, check_same_thread=False, isolation_level=None, timeout=30)
        try:
            with self._lock:
                version = _check_version(self._db, path)
                self._db.execute("PRAGMA journal_mode=WAL")
                self._db.execute("PRAGMA synchronous=NORMAL")
                if version < SCHEMA_VERSION:
                    self._migrate()
        except BaseException:
            self._db.close()
            raise

    def _migrate(self) -> None:
        """Bring the file to `SCHEMA_VERSION` in one transaction, running the migrations after
        its version (read again inside the transaction, so two gateways opening an old file at
        once migrate it once).

        A new file gets its tables; a file from before the version was kept has those of version
        1 already (`CREATE ... IF NOT EXISTS`) and goes on from there.
        """
        self._db.execute("BEGIN IMMEDIATE")
        try:
            version = _check_version(self._db, self.path)
            for target in range(version + 1, SCHEMA_VERSION + 1):
                for statement in _MIGRATIONS[target]:
                    self._db.execute(statement)
            self._db.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
        except BaseException:
            self._db.execute("ROLLBACK")
            raise
        self._db.execute("COMMIT")

    def close(self) -> None:
        """Close the database."""
        with self._lock:
            self._db.close()

    def _execute(self, sql: str, params: Sequence = ()) -> int:
        """Run one statement; the number of rows it changed (`JobDatabaseFull` when the disk
        under the database is full)."""
        with self._lock:
            try:
                return self._db.execute(sql, params).rowcount
            except sqlite3.OperationalError as exc:
                if _is_full(exc):
                    if self._db.in_transaction:  # give up the write lock the failed write held
                        self._db.rollback()
                    raise JobDatabaseFull(self.path) from exc
                raise

    def _query(self, sql: str, params: Sequence = ()) -> list[JobRecord]:
        with self._lock:
            rows = self._db.execute(
                f"SELECT {', '.join(_COLUMNS)} FROM jobs {sql}", params
            ).fetchall()
        return [_record(row) for row in rows]

    def create(
        self,
        job_id: str,
        kind: str,
        dataset: Path,
        sequences: Sequence[str],
        model: str | None = None,
        version: str | None = None,
        split: str | None = None,
        panoptic: bool = False,
    ) -> JobRecord:
        """Store a new queued job of the served model `model` (with a tables layout's `version`
        and `split`, where given; `panoptic` for one that finds objects too)."""
        now = time.time()
        self._execute(
            "INSERT INTO jobs (id, kind, state, dataset, sequences, created, model, version, "
            "split, panoptic) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
            (
                job_id,
                kind,
                JobState.queued.value,
                str(dataset),
                json.dumps(list(sequences)),
                now,
                model,
                version,
                split,
                int(panoptic),
            ),
        )
        return JobRecord(
            job_id,
            kind,
            JobState.queued,
            str(dataset),
            list(sequences),
            now,
            model=model,
            version=version,
            split=split,
            panoptic=panoptic,
        )

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

    def claim_next(self) -> JobRecord | None:
        """The oldest queued job, moved to running in the same step, so that two runners never
        take the same job; None when nothing is queued."""
        with self._lock:
            row = self._db.execute(
                "SELECT id FROM jobs WHERE state = ? ORDER BY created, rowid LIMIT 1",
                (JobState.queued.value,),
            ).fetchone()
            if row is None:
                return None
            self._db.execute(
                _START, (JobState.running.value, time.time(), row[0], JobState.queued.value)
            )
        return self.get(row[0])

    def count(self, state: JobState) -> int:
        """Number of jobs in `state`."""
        with self._lock:
            return int(
                self._db.execute(
                    "SELECT COUNT(*) FROM jobs WHERE state = ?", (state.value,)
                ).fetchone()[0]
            )

    def counts(self) -> dict[str, int]:
        """Number of jobs in each state."""
        with self._lock:
            rows = self._db.execute("SELECT state, COUNT(*) FROM jobs GROUP BY state").fetchall()
        found = dict(rows)
        return {s.value: int(found.get(s.value, 0)) for s in JobState}

    def start(self, job_id: str) -> bool:
        """queued -> running; False when the job is no longer queued. A resumed job keeps the time
        it first started."""
        return (
            self._execute(
                _START, (JobState.running.value, time.time(), job_id, JobState.queued.value)
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

    def next_submission(self, job_id: str) -> int:
        """Count a new submission of the job to a Ray cluster and return its number, stored
        before the job is submitted (a cluster refuses a submission id it has seen)."""
        with self._lock:
            self._db.execute("UPDATE jobs SET submission = submission + 1 WHERE id = ?", (job_id,))
            row = self._db.execute("SELECT submission FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if row is None:
            raise KeyError(job_id)
        return int(row[0])

    def requeue(self, job_id: str, graceful: bool = False) -> bool:
        """running -> queued, to be resumed. A `graceful` requeue (the gateway stopped cleanly)
        takes back the start it counted, so that only unclean stops count towards the limit."""
        counted = "MAX(attempts - 1, 0)" if graceful else "attempts"
        return (
            self._execute(
                f"UPDATE jobs SET state = ?, attempts = {counted} WHERE id = ? AND state = ?",
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


def _is_full(exc: sqlite3.Error) -> bool:
    """Whether SQLite failed for want of disk space (SQLITE_FULL, or an I/O error on a full
    disk)."""
    code = getattr(exc, "sqlite_errorname", "")
    return code.startswith("SQLITE_FULL") or "disk is full" in str(exc)


def _record(row: Sequence) -> JobRecord:
    values = dict(zip(_COLUMNS, row, strict=True))
    values["state"] = JobState(values["state"])
    values["sequences"] = json.loads(values["sequences"])
    values["errors"] = json.loads(values["errors"])
    values["metrics"] = json.loads(values["metrics"]) if values["metrics"] else None
    values["panoptic"] = bool(values["panoptic"])
    return JobRecord(**values)
