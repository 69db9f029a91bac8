"""Jobs over whole sequences, in five parts.

- `store`: `JobRecord` and `JobStore`, every job's state, progress, results and submissions in
  SQLite, with the schema version of the file;
- `executors`: the `JobExecutor` protocol, `LocalExecutor` (in this process), the `JobControl`
  the runner stops a job by, and `write_predictions_zip`, the zip of a job's predictions;
- `ray_jobs`: `RayJobExecutor`, each job a Ray job submitted through a cluster's Jobs API (Ray
  is imported only when it is used);
- `capacity`: `JobRefused` and the queue and disk bounds a new job must fit in;
- `manager`: `JobManager`, which admits, queues, runs, cancels, resumes and expires jobs.
"""

from service.jobs.capacity import JobRefused, disk_full, expected_output_bytes
from service.jobs.executors import (
    JobControl,
    JobError,
    JobExecutor,
    LocalExecutor,
    write_predictions_zip,
)
from service.jobs.manager import JobManager
from service.jobs.store import (
    SCHEMA_VERSION,
    JobDatabaseError,
    JobDatabaseFull,
    JobDatabaseVersionError,
    JobRecord,
    JobStore,
    check_job_database,
)

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
    "LocalExecutor",
    "check_job_database",
    "disk_full",
    "expected_output_bytes",
    "write_predictions_zip",
]
