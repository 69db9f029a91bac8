"""The job manager on its own: jobs run to success in the gateway's profile, cancellation,
recovery after a crash, retention, side-by-side runs with the queue and disk bounds, and the
read roots checked again when a job runs."""

from __future__ import annotations

import json
import os
import threading
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from rangeret.dataset.layout import KITTI_LAYOUT, prediction_path
from rangeret.dataset.profiles import load_profile
from rangeret.dataset.selection import DatasetSelection
from rangeret.io.scans import write_labels
from rangeret.sim import simulate_dataset
from service.jobs import JobManager, JobStore
from service.jobs.errors import NoRoom, QueueFull
from service.schemas import JobState
from tests.support.apps import one_model
from tests.support.jobs import FakeExecutor, wait_state
from tests.support.trees import make_tree

PANDASET = load_profile("pandaset")


def _manager(tmp_path: Path, executor=None, retention: float = 3600, profile=None) -> JobManager:
    return JobManager(
        JobStore(tmp_path / "jobs.sqlite"),
        executor or FakeExecutor(),
        tmp_path / "jobs",
        retention,
        models=one_model(profile or load_profile("semantickitti")),
    )


def test_job_runs_to_success_with_predictions_and_report(tmp_path):
    data = tmp_path / "data"
    make_tree(data, {"08": [30, 40]})
    manager = _manager(tmp_path)
    manager.start()
    try:
        job_id, _ = manager.new_job()
        manager.submit(job_id, "dataset", DatasetSelection.named(data, ["08"], KITTI_LAYOUT))
        assert (
            wait_state(manager, job_id, JobState.succeeded, JobState.failed) is JobState.succeeded
        )
    finally:
        manager.stop()
    record = manager.store.get(job_id)
    assert (record.total, record.done, record.failed) == (2, 2, 0)
    assert Path(record.predictions).is_file() and Path(record.report).is_file()
    assert set(record.metrics) == {"miou", "accuracy", "iou"}
    report = json.loads(Path(record.report).read_text())
    assert (report["precision"], report["backend"]) == ("fp32", "torch")


def test_a_job_reads_evaluates_and_zips_in_the_profile_of_the_gateway(tmp_path):
    data = tmp_path / "data"
    profile = PANDASET.with_overrides(height=8, width=32)
    simulate_dataset(data, {"1": 2, "2": 1}, labelled=["1"], profile=profile)
    manager = _manager(tmp_path, FakeExecutor(PANDASET.points.point_bytes), profile=PANDASET)
    manager.start()
    try:
        job_id, folder = manager.new_job()
        manager.submit(
            job_id, "dataset", DatasetSelection.named(data, ["001", "002"], PANDASET.layout)
        )
        assert (
            wait_state(manager, job_id, JobState.succeeded, JobState.failed) is JobState.succeeded
        ), manager.store.get(job_id).reason
    finally:
        manager.stop()
    record = manager.store.get(job_id)
    assert (record.total, record.done, record.failed) == (3, 3, 0)
    assert set(record.metrics["iou"]) <= set(PANDASET.labels.class_names)
    report = json.loads(Path(record.report).read_text())
    assert report["profile"] == "pandaset" and report["sequences"] == ["001"]
    with zipfile.ZipFile(record.predictions) as zf:
        assert "sequences/002/predictions/000000.label" in zf.namelist()
        assert "profile: pandaset" in zf.read("description.txt").decode()
    assert (folder / "profile.txt").read_text().strip() == "pandaset"


def test_a_job_accepted_for_another_profile_fails_naming_both(tmp_path):
    data = tmp_path / "data"
    make_tree(data, {"08": [30]}, labelled=False)
    first = _manager(tmp_path)
    job_id, folder = first.new_job()
    first.submit(job_id, "dataset", DatasetSelection.named(data, ["08"], KITTI_LAYOUT))
    first.store.close()
    second = _manager(tmp_path, profile=PANDASET)
    second.start()
    try:
        assert wait_state(second, job_id, JobState.failed, JobState.succeeded) is JobState.failed
    finally:
        second.stop()
    reason = second.store.get(job_id).reason
    assert "semantickitti" in reason and "pandaset" in reason, reason
    assert not (folder / "predictions").exists()


def test_cancel_a_running_job_removes_its_files(tmp_path):
    data = tmp_path / "data"
    make_tree(data, {"08": [30, 40]}, labelled=False)
    executor = FakeExecutor()
    executor.release.clear()
    manager = _manager(tmp_path, executor)
    manager.start()
    try:
        job_id, folder = manager.new_job()
        manager.submit(job_id, "dataset", DatasetSelection.named(data, ["08"], KITTI_LAYOUT))
        assert executor.started.wait(30)
        assert manager.cancel(job_id).state is JobState.cancelled
        executor.release.set()
        deadline = time.time() + 30
        while folder.exists() and time.time() < deadline:
            time.sleep(0.02)
        assert not folder.exists() and manager.store.get(job_id).state is JobState.cancelled
        assert manager.cancel(job_id).state is JobState.cancelled  # finished: now forgotten
        assert manager.store.get(job_id) is None and manager.cancel(job_id) is None
    finally:
        manager.stop()


def test_recovery_after_a_crash(tmp_path):
    data = tmp_path / "data"
    make_tree(data, {"08": [30]}, labelled=False)
    manager = _manager(tmp_path)
    store = manager.store
    resumable, gone, tired = manager.new_job()[0], manager.new_job()[0], manager.new_job()[0]
    for job_id, dataset in ((resumable, data), (gone, tmp_path / "deleted"), (tired, data)):
        store.create(job_id, "dataset", dataset, ["08"])
        store.start(job_id)
    for _ in range(2):
        store.requeue(tired)
        store.start(tired)
    orphan = manager.job_dir(manager.new_job()[0])  # an upload cut short: the gateway's, unrecorded
    lookalike = manager.jobs_dir / ("0" * 32)  # a job id's name, but not made by the gateway
    lookalike.mkdir()
    manager.recover()
    assert store.get(resumable).state is JobState.queued
    assert store.get(gone).state is JobState.failed and "no longer exists" in store.get(gone).reason
    assert store.get(tired).state is JobState.failed and "3 times" in store.get(tired).reason
    assert not orphan.exists() and manager.job_dir(resumable).exists() and lookalike.is_dir()


def test_retention_removes_old_finished_jobs_only(tmp_path):
    manager = _manager(tmp_path, retention=60)
    store = manager.store
    old, recent, running = manager.new_job()[0], manager.new_job()[0], manager.new_job()[0]
    for job_id in (old, recent, running):
        store.create(job_id, "dataset", tmp_path, ["08"])
        store.start(job_id)
    store.finish(old, JobState.succeeded)
    store.finish(recent, JobState.failed, reason="x")
    assert manager.sweep(now=time.time() + 30) == 0
    store._execute("UPDATE jobs SET finished = finished - 100 WHERE id = ?", (old,))
    assert manager.sweep() == 1
    assert store.get(old) is None and not manager.job_dir(old).exists()
    assert store.get(recent) is not None and store.get(running).state is JobState.running
    assert store.counts() == {
        "queued": 0,
        "running": 1,
        "succeeded": 0,
        "failed": 1,
        "cancelled": 0,
    }


class PerJobExecutor(FakeExecutor):
    """A `FakeExecutor` that holds the jobs over the sequences in `held` until released (or
    cancelled), and runs the others at once."""

    def __init__(self, held: set[str]) -> None:
        super().__init__()
        self.held = held
        self.release.clear()
        self.holding = threading.Semaphore(0)

    def predict(self, entries, dataset, sequences, out, progress, cancel, model=None):
        if self.held & set(sequences):
            self.holding.release()
            while not self.release.wait(0.05) and not cancel.is_set():
                pass
        for i, entry in enumerate(entries):
            n = os.path.getsize(entry.scan_path) // self.point_bytes
            write_labels(
                prediction_path(out, entry.sequence, entry.name), np.zeros(n, dtype=np.uint32)
            )
            progress(i + 1, 0, len(entries))
        return {}


def test_jobs_run_side_by_side_and_the_queue_and_disk_are_bounded(tmp_path):
    data = tmp_path / "data"
    make_tree(data, {"08": [30], "09": [40, 50]}, labelled=False)
    executor = PerJobExecutor(held={"09"})
    manager = JobManager(
        JobStore(tmp_path / "jobs.sqlite"),
        executor,
        tmp_path / "jobs",
        3600,
        max_running=2,
        max_queued=1,
        max_bytes=10_000,
        read_roots=[tmp_path],
        models=one_model(load_profile("semantickitti")),
    )

    def submit(sequence: str, expected: int) -> str:
        job_id, _ = manager.new_job()
        manager.submit(
            job_id,
            "dataset",
            DatasetSelection.named(data, [sequence], KITTI_LAYOUT),
            expected_bytes=expected,
        )
        return job_id

    manager.start()
    try:
        long_id = submit("09", 4_000)
        assert executor.holding.acquire(timeout=10)
        short_id = submit("08", 100)
        assert wait_state(manager, short_id, JobState.succeeded) is JobState.succeeded
        assert manager.store.get(long_id).state is JobState.running

        second_id = submit("09", 4_000)
        assert executor.holding.acquire(timeout=10)
        queued_id = submit("08", 100)
        assert manager.store.get(queued_id).state is JobState.queued
        with pytest.raises(QueueFull) as full:
            submit("08", 100)
        assert "RANGERET_MAX_QUEUED_JOBS" in str(full.value)
        manager.cancel(queued_id)
        with pytest.raises(NoRoom) as disk:
            submit("08", 3_000)
        assert "RANGERET_MAX_JOB_BYTES" in str(disk.value)
        assert submit("08", 1_000)
        executor.release.set()
        for job_id in (long_id, second_id):
            assert wait_state(manager, job_id, JobState.succeeded) is JobState.succeeded
    finally:
        executor.release.set()
        manager.stop()


def test_a_job_whose_files_were_linked_out_of_the_roots_since_it_was_queued_fails(tmp_path):
    roots = tmp_path / "roots"
    data = roots / "data"
    make_tree(data, {"08": [30, 40]}, labelled=False)
    outside = tmp_path / "outside.bin"
    outside.write_bytes(b"\0" * 16 * 30)
    scan = data / "sequences" / "08" / "velodyne" / "000001.bin"
    scan.unlink()
    scan.symlink_to(outside)
    manager = JobManager(
        JobStore(tmp_path / "jobs.sqlite"), FakeExecutor(), tmp_path / "jobs", 3600,
        read_roots=[roots], models=one_model(load_profile("semantickitti")),
    )  # fmt: skip
    manager.start()
    try:
        job_id, _ = manager.new_job()
        manager.submit(job_id, "dataset", DatasetSelection.named(data, ["08"], KITTI_LAYOUT))
        assert wait_state(manager, job_id, JobState.failed) is JobState.failed
    finally:
        manager.stop()
    reason = manager.store.get(job_id).reason
    assert "08/000001" in reason and "outside the data roots" in reason
    assert str(tmp_path) not in reason
