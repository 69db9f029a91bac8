"""Parts of the gateway on their own: archive checks, the request batcher, the job store and
runner (recovery, cancellation, retention), settings and content negotiation."""

from __future__ import annotations

import asyncio
import io
import json
import os
import tarfile
import threading
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from rangeret.dataset.layout import list_scans, prediction_path
from rangeret.dataset.profiles import load_profile
from rangeret.inference.results import ScanPrediction
from rangeret.io.scans import write_labels
from rangeret.sim import simulate_dataset
from rangeret.submission.archives import required_directories
from service.archives import ArchiveError, ArchiveLimits, ArchiveTooLarge, extract_archive
from service.batching import BackendError, ScanBatcher, ScanRejected
from service.errors import validation_sentence
from service.jobs import JobManager, JobRefused, JobStore, write_predictions_zip
from service.routes.scans import wants_json
from service.schemas import JobState
from service.settings import Settings, is_loopback
from tests.support.trees import make_tree

LIMITS = ArchiveLimits(
    max_bytes=1 << 20, max_members=20, max_points=1000, max_extracted_bytes=1 << 20
)
SCAN = np.arange(40, dtype=np.float32).reshape(10, 4).tobytes()
PANDASET = load_profile("pandaset")


# Archives --------------------------------------------------------------------------------------


def _zip(tmp_path: Path, members: dict[str, bytes]) -> Path:
    path = tmp_path / "upload"
    with zipfile.ZipFile(path, "w") as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return path


def test_archive_with_labels_is_extracted(tmp_path):
    labels = np.full(10, 40, dtype=np.uint32).tobytes()
    archive = _zip(
        tmp_path,
        {
            "sequences/": b"",
            "sequences/08/velodyne/000000.bin": SCAN,
            "./sequences/08/labels/000000.label": labels,
            "sequences/11/velodyne/000000.bin": SCAN,
            "sequences/11/velodyne/000001.bin": SCAN,
        },
    )
    found = extract_archive(archive, tmp_path / "data", LIMITS)
    assert found.sequences == ["08", "11"] and found.labelled == ["08"] and found.scans == 3
    assert (
        tmp_path / "data" / "sequences" / "08" / "labels" / "000000.label"
    ).read_bytes() == labels
    assert len(list_scans(found.root, found.sequences)) == 3


@pytest.mark.parametrize(
    ("members", "words"),
    [
        (
            {
                "sequences/08/velodyne/000000.bin": SCAN,
                "sequences/08/labels/000001.label": b"\0" * 40,
            },
            "no matching scan",
        ),
        (
            {
                "sequences/08/velodyne/000000.bin": SCAN,
                "sequences/08/labels/000000.label": b"\0" * 36,
            },
            "holds 9 labels",
        ),
        (
            {
                "sequences/08/velodyne/000000.bin": SCAN,
                "sequences/08/velodyne/000001.bin": SCAN,
                "sequences/08/labels/000000.label": b"\0" * 40,
            },
            "not for 1",
        ),
        ({"sequences\\08\\velodyne\\000000.bin": SCAN}, "escape"),
        ({"C:/sequences/08/velodyne/000000.bin": SCAN}, "escape"),
        ({"data/sequences/08/velodyne/000000.bin": SCAN}, "not a sequences"),
        ({"sequences/08/velodyne/000000.label": SCAN}, "not a sequences"),
        ({"sequences/08/other/": b""}, "folder outside"),
        ({"sequences/08/velodyne/000000.bin": SCAN[:-1]}, "multiple of 16"),
        ({}, "no scan"),
    ],
)
def test_bad_archive_members(tmp_path, members, words):
    with pytest.raises(ArchiveError, match=words):
        extract_archive(_zip(tmp_path, members), tmp_path / "data", LIMITS)


def test_archive_limits_are_checked_before_writing(tmp_path):
    many = {f"sequences/08/velodyne/{i:06d}.bin": SCAN for i in range(21)}
    with pytest.raises(ArchiveTooLarge, match="members"):
        extract_archive(_zip(tmp_path, many), tmp_path / "a", LIMITS)
    assert not (tmp_path / "a").exists()
    big = {"sequences/08/velodyne/000000.bin": b"\0" * 16 * 1001}
    with pytest.raises(ArchiveTooLarge, match="1,000 points"):
        extract_archive(_zip(tmp_path, big), tmp_path / "b", LIMITS)
    total = {f"sequences/08/velodyne/{i:06d}.bin": b"\0" * 16000 for i in range(10)}
    with pytest.raises(ArchiveTooLarge, match="add up"):
        extract_archive(
            _zip(tmp_path, total), tmp_path / "c", ArchiveLimits(1 << 20, 20, 1000, 100_000)
        )


def test_tar_duplicates_and_special_members_are_refused(tmp_path):
    def tar(*members: tuple[str, bytes, bytes]) -> Path:
        path = tmp_path / "upload.tar"
        with tarfile.open(path, "w") as tf:
            for name, data, kind in members:
                info = tarfile.TarInfo(name)
                info.type, info.size = kind, len(data)
                tf.addfile(info, io.BytesIO(data))
        return path

    name = "sequences/08/velodyne/000000.bin"
    with pytest.raises(ArchiveError, match="more than once"):
        extract_archive(
            tar((name, SCAN, tarfile.REGTYPE), (name, SCAN, tarfile.REGTYPE)),
            tmp_path / "d",
            LIMITS,
        )
    with pytest.raises(ArchiveError, match="pipe"):
        extract_archive(tar((name, b"", tarfile.FIFOTYPE)), tmp_path / "d", LIMITS)
    with pytest.raises(ArchiveError, match=r"not a \.zip"):
        extract_archive(_write(tmp_path, b"junk" * 200), tmp_path / "d", LIMITS)


def test_archive_of_another_profile_is_checked_with_its_record_and_laid_out_as_its_datasets(
    tmp_path,
):
    record, layout = PANDASET.points, PANDASET.layout
    scan5 = np.arange(50, dtype=np.float32).reshape(10, 5).tobytes()
    archive = _zip(
        tmp_path,
        {
            "sequences/001/velodyne/000000.bin": scan5,
            "sequences/001/labels/000000.label": np.full(10, 13, dtype=np.uint32).tobytes(),
        },
    )
    found = extract_archive(archive, tmp_path / "data", LIMITS, record=record, layout=layout)
    assert found.sequences == ["001"] and found.labelled == ["001"]
    assert (tmp_path / "data" / "001" / "velodyne" / "000000.bin").read_bytes() == scan5
    assert len(list_scans(found.root, found.sequences, layout=layout)) == 1
    with pytest.raises(ArchiveError, match=r"multiple of 20 \(5 float32 per point: .*laser_id"):
        extract_archive(
            _zip(tmp_path, {"sequences/001/velodyne/000000.bin": SCAN[:144]}),  # 9 x 16 bytes
            tmp_path / "four",
            LIMITS,
            record=record,
            layout=layout,
        )
    big = {"sequences/001/velodyne/000000.bin": b"\0" * 20 * 1001}
    with pytest.raises(ArchiveTooLarge, match="1,000 points"):
        extract_archive(_zip(tmp_path, big), tmp_path / "big", LIMITS, record=record, layout=layout)
    fits = {"sequences/001/velodyne/000000.bin": b"\0" * 20 * 1000}
    assert (
        extract_archive(_zip(tmp_path, fits), tmp_path / "fits", LIMITS, record=record).scans == 1
    )


def _write(tmp_path: Path, data: bytes) -> Path:
    path = tmp_path / "junk"
    path.write_bytes(data)
    return path


# Batching --------------------------------------------------------------------------------------


class FakePool:
    """Labels = the number of points, repeated; records every batch; can be told to fail."""

    def __init__(self, delay: float = 0.05) -> None:
        self.delay = delay
        self.batches: list[tuple[int, bool]] = []
        self.confidences: list[bool] = []
        self.fail = False
        self.in_flight = 0

    async def predict_async(self, scans, knn=True, confidence=False):
        self.batches.append((len(scans), knn))
        self.confidences.append(confidence)
        self.in_flight += 1
        try:
            await asyncio.sleep(self.delay)
            if self.fail:
                raise RuntimeError("actor died")
            return [
                ScanPrediction(
                    np.full(len(s), len(s) + (0 if knn else 1000), dtype=np.uint32),
                    np.full(len(s), 0.5, dtype=np.float32) if confidence else None,
                )
                for s in scans
            ]
        finally:
            self.in_flight -= 1

    def queue_depth(self):
        return self.in_flight


def _scan(n: int) -> np.ndarray:
    return np.zeros((n, 4), dtype=np.float32)


def test_batcher_gathers_concurrent_requests_up_to_the_batch_size():
    async def run():
        pool = FakePool()
        batcher = ScanBatcher(pool, batch_size=4, max_wait=0.05)
        await batcher.start()
        try:
            results = await asyncio.gather(
                *(batcher.label(_scan(n), knn=n % 2 == 0) for n in range(1, 12))
            )
        finally:
            await batcher.stop()
        return pool, results

    pool, results = asyncio.run(run())
    for n, labelled in enumerate(results, start=1):
        assert labelled.labels.tolist() == [n + (0 if n % 2 == 0 else 1000)] * n
        assert labelled.confidence is None
    assert all(size <= 4 for size, _ in pool.batches) and sum(s for s, _ in pool.batches) == 11
    assert max(size for size, _ in pool.batches) > 1 and len(pool.batches) < 11


def test_batcher_waits_at_most_max_wait_and_not_at_all_for_batch_size_one():
    async def one(batch_size: int) -> float:
        batcher = ScanBatcher(FakePool(delay=0), batch_size=batch_size, max_wait=0.2)
        await batcher.start()
        start = time.perf_counter()
        await batcher.label(_scan(3))
        elapsed = time.perf_counter() - start
        await batcher.stop()
        return elapsed

    assert 0.18 <= asyncio.run(one(4)) < 1.0
    assert asyncio.run(one(1)) < 0.1


def test_batcher_reports_backend_failures_and_keeps_serving():
    async def run():
        pool = FakePool(delay=0.01)
        batcher = ScanBatcher(pool, batch_size=2, max_wait=0.01)
        await batcher.start()
        pool.fail = True
        with pytest.raises(BackendError, match="actor died"):
            await batcher.label(_scan(2))
        pool.fail = False
        labels = await batcher.label(_scan(2))
        await batcher.stop()
        return labels

    assert asyncio.run(run()).labels.tolist() == [2, 2]


class RejectingPool(FakePool):
    """Refuses every scan of 3 points, as a worker refuses a scan it cannot project."""

    async def predict_async(self, scans, knn=True, confidence=False):
        labels = await super().predict_async(scans, knn, confidence)
        return [
            "a laser id is off the image" if len(s) == 3 else out
            for s, out in zip(scans, labels, strict=True)
        ]


def test_batcher_refuses_one_scan_and_labels_the_rest_of_its_batch():
    async def run():
        pool = RejectingPool(delay=0.01)
        batcher = ScanBatcher(pool, batch_size=4, max_wait=0.05)
        await batcher.start()
        try:
            return pool, await asyncio.gather(
                *(batcher.label(_scan(n)) for n in (2, 3, 4)), return_exceptions=True
            )
        finally:
            await batcher.stop()

    pool, (two, three, four) = asyncio.run(run())
    assert pool.batches == [(3, True)]
    assert isinstance(three, ScanRejected) and "laser id" in str(three)
    assert two.labels.tolist() == [2, 2] and four.labels.tolist() == [4] * 4


def test_batcher_never_mixes_requests_for_confidences_with_others():
    async def run():
        pool = FakePool(delay=0.02)
        batcher = ScanBatcher(pool, batch_size=8, max_wait=0.05)
        await batcher.start()
        try:
            results = await asyncio.gather(
                *(batcher.label(_scan(n), confidence=n % 2 == 0) for n in range(1, 9))
            )
        finally:
            await batcher.stop()
        return pool, results

    pool, results = asyncio.run(run())
    for n, labelled in enumerate(results, start=1):
        assert (labelled.confidence is not None) == (n % 2 == 0)
        if labelled.confidence is not None:
            assert labelled.confidence.shape == (n,)
    assert sorted(pool.confidences) == [False, True]  # one batch of each


# Jobs ------------------------------------------------------------------------------------------


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

    def predict(self, entries, dataset, sequences, out, progress, cancel):
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


def _manager(tmp_path: Path, executor=None, retention: float = 3600, profile=None) -> JobManager:
    return JobManager(
        JobStore(tmp_path / "jobs.sqlite"),
        executor or FakeExecutor(),
        tmp_path / "jobs",
        retention,
        profile=profile,
    )


def _wait_state(
    manager: JobManager, job_id: str, *states: JobState, timeout: float = 30
) -> JobState:
    deadline = time.time() + timeout
    while time.time() < deadline:
        state = manager.store.get(job_id).state
        if state in states:
            return state
        time.sleep(0.02)
    raise AssertionError(f"job {job_id} stayed {manager.store.get(job_id).state}")


def test_job_runs_to_success_with_predictions_and_report(tmp_path):
    data = tmp_path / "data"
    make_tree(data, {"08": [30, 40]})
    manager = _manager(tmp_path)
    manager.start()
    try:
        job_id, _ = manager.new_job()
        manager.submit(job_id, "dataset", data, ["08"])
        assert (
            _wait_state(manager, job_id, JobState.succeeded, JobState.failed) is JobState.succeeded
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
        manager.submit(job_id, "dataset", data, ["001", "002"])
        assert (
            _wait_state(manager, job_id, JobState.succeeded, JobState.failed) is JobState.succeeded
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
    first.submit(job_id, "dataset", data, ["08"])
    first.store.close()
    second = _manager(tmp_path, profile=PANDASET)
    second.start()
    try:
        assert _wait_state(second, job_id, JobState.failed, JobState.succeeded) is JobState.failed
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
        manager.submit(job_id, "dataset", data, ["08"])
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


def test_predictions_zip_directory_entries(tmp_path):
    make_tree(tmp_path / "data", {"08": [5], "11": [6]})
    pred = tmp_path / "pred"
    entries = list_scans(tmp_path / "data", ["08", "11"])
    for entry in entries:
        write_labels(
            prediction_path(pred, entry.sequence, entry.name), np.zeros(5, dtype=np.uint32)
        )
    test_only = [e for e in entries if e.sequence == "11"]
    write_predictions_zip(pred, test_only, ["11"], tmp_path / "a.zip", "d")
    write_predictions_zip(pred, entries, ["08", "11"], tmp_path / "b.zip", "d")
    names_a = zipfile.ZipFile(tmp_path / "a.zip").namelist()
    names_b = zipfile.ZipFile(tmp_path / "b.zip").namelist()
    assert [n for n in names_a if n.endswith("/")] == list(required_directories())
    assert [n for n in names_b if n.endswith("/")] == [
        "sequences/",
        "sequences/08/",
        "sequences/08/predictions/",
        "sequences/11/",
        "sequences/11/predictions/",
    ]
    assert "sequences/08/predictions/000000.label" in names_b and "description.txt" in names_a


# Settings, negotiation, messages -------------------------------------------------------------


def test_settings_from_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("RANGERET_DATA_ROOTS", f"{tmp_path}{os.pathsep}{tmp_path / 'b'}")
    monkeypatch.setenv("RANGERET_API_TOKEN", "")
    monkeypatch.setenv("RANGERET_RETENTION", "90")
    settings = Settings()
    assert settings.data_roots == [tmp_path.resolve(), (tmp_path / "b").resolve()]
    assert settings.token is None and settings.retention.total_seconds() == 90
    assert settings.address_problem() is None
    assert "RANGERET_API_TOKEN" in Settings(host="0.0.0.0").address_problem()
    assert Settings(host="0.0.0.0", api_token="t").address_problem() is None
    monkeypatch.setenv("RANGERET_DATA_ROOTS", f'["{tmp_path}"]')
    assert Settings().data_roots == [tmp_path.resolve()]
    assert is_loopback("127.0.0.2") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("10.0.0.1") and not is_loopback("example.org")


@pytest.mark.parametrize(
    ("accept", "json"),
    [
        (None, False),
        ("*/*", False),
        ("application/json", True),
        ("application/json, */*", True),
        ("application/octet-stream, application/json", False),
        ("application/octet-stream;q=0.5, application/json", True),
        ("application/json;q=0", False),
        ("text/html", False),
    ],
)
def test_accept_negotiation(accept, json):
    assert wants_json(accept) is json


def test_validation_sentences():
    errors = [
        {"loc": ("query", "knn"), "msg": "Input should be a valid boolean"},
        {"loc": ("body",), "msg": "x"},
    ]
    assert validation_sentence(errors) == (
        "The query parameter 'knn' is invalid: Input should be a valid boolean (and 1 more problem(s))."
    )
    assert validation_sentence(
        [{"loc": (), "msg": "Value error, give either 'split' or 'sequences'"}], "body"
    ) == ("The request body is invalid: give either 'split' or 'sequences'.")


class PerJobExecutor(FakeExecutor):
    """A `FakeExecutor` that holds the jobs over the sequences in `held` until released (or
    cancelled), and runs the others at once."""

    def __init__(self, held: set[str]) -> None:
        super().__init__()
        self.held = held
        self.release.clear()
        self.holding = threading.Semaphore(0)

    def predict(self, entries, dataset, sequences, out, progress, cancel):
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


def test_claims_take_the_oldest_queued_job_once_and_a_resumed_job_keeps_its_start(tmp_path):
    store = JobStore(tmp_path / "jobs.sqlite")
    for name in ("a", "b", "c"):
        store.create(name, "dataset", tmp_path, ["08"])
        time.sleep(0.01)
    claimed = [store.claim_next() for _ in range(4)]
    assert [r.id if r else None for r in claimed] == ["a", "b", "c", None]
    assert all(r.state is JobState.running and r.attempts == 1 for r in claimed[:3])
    first_start = store.get("a").started
    assert store.requeue("a") and store.start("a")
    assert store.get("a").started == first_start and store.get("a").attempts == 2


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
    )

    def submit(sequence: str, expected: int) -> str:
        job_id, _ = manager.new_job()
        manager.submit(job_id, "dataset", data, [sequence], expected_bytes=expected)
        return job_id

    manager.start()
    try:
        long_id = submit("09", 4_000)
        assert executor.holding.acquire(timeout=10)
        short_id = submit("08", 100)
        assert _wait_state(manager, short_id, JobState.succeeded) is JobState.succeeded
        assert manager.store.get(long_id).state is JobState.running

        second_id = submit("09", 4_000)
        assert executor.holding.acquire(timeout=10)
        queued_id = submit("08", 100)
        assert manager.store.get(queued_id).state is JobState.queued
        with pytest.raises(JobRefused) as full:
            submit("08", 100)
        assert full.value.status_code == 429 and "RANGERET_MAX_QUEUED_JOBS" in str(full.value)
        manager.cancel(queued_id)
        with pytest.raises(JobRefused) as disk:
            submit("08", 3_000)
        assert disk.value.status_code == 507 and "RANGERET_MAX_JOB_BYTES" in str(disk.value)
        assert submit("08", 1_000)
        executor.release.set()
        for job_id in (long_id, second_id):
            assert _wait_state(manager, job_id, JobState.succeeded) is JobState.succeeded
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
        read_roots=[roots],
    )  # fmt: skip
    manager.start()
    try:
        job_id, _ = manager.new_job()
        manager.submit(job_id, "dataset", data, ["08"])
        assert _wait_state(manager, job_id, JobState.failed) is JobState.failed
    finally:
        manager.stop()
    reason = manager.store.get(job_id).reason
    assert "08/000001" in reason and "outside the data roots" in reason
    assert str(tmp_path) not in reason
