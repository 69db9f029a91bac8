"""Stand-ins for the job tests that run without a gateway: an executor that writes all-zero
predictions, and a wait for a job's state."""

from __future__ import annotations

import os
import threading
import time

import numpy as np

from rangeret.dataset.layout import prediction_path
from rangeret.io.scans import write_labels
from service.jobs import JobManager
from service.schemas import JobState


class FakeExecutor:
    """Writes all-zero predictions of the right length; can block until released."""

    backend = "fake"
    precision = "fp32"
    inference_backend = "torch"

    def __init__(self, point_bytes: int = 16) -> None:
        self.point_bytes = point_bytes
        self.release = threading.Event()
        self.release.set()
        self.started = threading.Event()

    def predict(self, entries, dataset, sequences, out, progress, cancel, model=None):
        self.started.set()
        self.release.wait(30)
        for i, entry in enumerate(entries):
            if cancel.is_set():
                break
            n = os.path.getsize(entry.scan_path) // self.point_bytes
            write_labels(
                prediction_path(out, entry.sequence, entry.name), np.zeros(n, dtype=np.uint32)
            )
            progress(i + 1, 0, len(entries))
        return {}


def wait_state(
    manager: JobManager, job_id: str, *states: JobState, timeout: float = 30
) -> JobState:
    deadline = time.time() + timeout
    while time.time() < deadline:
        state = manager.store.get(job_id).state
        if state in states:
            return state
        time.sleep(0.02)
    raise AssertionError(f"job {job_id} stayed {manager.store.get(job_id).state}")
