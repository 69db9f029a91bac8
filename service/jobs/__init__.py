"""Jobs over whole sequences, in four parts.

- `store`: `JobRecord` and `JobStore`, every job's state, progress and results in SQLite, with the
  schema version of the file;
- `executors`: `LocalExecutor` (in this process) and `RayExecutor` (on the Ray cluster), which run
  the network over a job's scans, and `write_predictions_zip`, the zip of its predictions;
- `capacity`: `JobRefused` and the queue and disk bounds a new job must fit in;
- `manager`: `JobManager`, which admits, queues, runs, cancels, resumes and expires jobs.
"""

from service.jobs.capacity import JobRefused, disk_full, expected_output_bytes
from service.jobs.executors import JobExecutor, LocalExecutor, RayExecutor, write_predictions_zip
from service.jobs.manager import JobManager
from service.jobs.store import (
    SCHEMA_VERSION,
    JobDatabaseVersionError,
    JobRecord,
    JobStore,
    check_schema_version,
)

__all__ = [
    "SCHEMA_VERSION",
    "JobDatabaseVersionError",
    "JobExecutor",
    "JobManager",
    "JobRecord",
    "JobRefused",
    "JobStore",
    "LocalExecutor",
    "RayExecutor",
    "check_schema_version",
    "disk_full",
    "expected_output_bytes",
    "write_predictions_zip",
]
