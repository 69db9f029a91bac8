"""Jobs over whole sequences: the scheduler, the service layer that does a job's work, and
what they build on.

- `store`: `JobRecord` and `JobStore`, every job's state, progress, results and submissions in
  SQLite, with the schema version of the file;
- `executors`: the `JobExecutor` protocol, `LocalExecutor` (in this process) and the
  `JobControl` the runner stops a job by;
- `ray_jobs`: `RayJobExecutor`, each job a Ray job submitted through a cluster's Jobs API (Ray
  is imported only when it is used);
- `errors`: what goes wrong when a job is asked for (`BadJobRequest`, `JobRefused`, ...), said
  without HTTP: the routes answer each with its status;
- `capacity`: the queue and disk bounds a new job must fit in;
- `intake`: `JobIntake`, a new job's folder prepared from an upload or a dataset on the server,
  checked and queued;
- `work`: `JobWork`, a claimed job's work: predict, check, zip, evaluate, final record;
- `results`: a job's result files, `write_predictions_zip` among them, and the report's plots;
- `reasons`: the one-line reasons a failed job is stored with;
- `manager`: `JobManager`, which admits, queues, runs (through `JobWork`), cancels, resumes and
  expires jobs.
"""

from service.jobs.capacity import disk_full, expected_output_bytes
from service.jobs.errors import JobRefused
from service.jobs.executors import JobControl, JobError, JobExecutor, LocalExecutor
from service.jobs.manager import JobManager
from service.jobs.results import write_predictions_zip
from service.jobs.store import (
    SCHEMA_VERSION,
    JobDatabaseError,
    JobDatabaseFull,
    JobDatabaseVersionError,
    JobRecord,
    JobStore,
    check_job_database,
)
from service.jobs.work import JobWork

__all__ = [
    "SCHEMA_VERSION",
    "JobControl",
    "JobDatabaseError",
    "JobDatabaseFull",
    "JobDatabaseVersionError",
    "JobError",
    "JobExecutor",
    "JobManager",
    "JobRecord",
    "JobRefused",
    "JobStore",
    "JobWork",
    "LocalExecutor",
    "check_job_database",
    "disk_full",
    "expected_output_bytes",
    "write_predictions_zip",
]
