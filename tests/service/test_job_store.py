"""The job store's schema version (stamped, migrated, checked, refused when newer), its submission
counter, and the rule that no SQLite call runs on the gateway's event loop."""

from __future__ import annotations

import asyncio
import functools
import io
import os
import sqlite3
import threading
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from rangeret.dataset.layout import KITTI_LAYOUT, prediction_path
from rangeret.dataset.profiles import load_profile
from rangeret.inference.results import ScanPrediction
from rangeret.io.scans import write_labels
from service.app import create_app
from service.jobs import SCHEMA_VERSION, JobDatabaseVersionError, JobStore
from service.schemas import JobState
from service.settings import Settings
from tests.support.apps import one_model
from tests.support.trees import make_tree

TOKEN = "store-test-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def _user_version(path: Path) -> int:
    db = sqlite3.connect(path)
    try:
        return db.execute("PRAGMA user_version").fetchone()[0]
    finally:
        db.close()


def _set_user_version(path: Path, version: int) -> None:
    db = sqlite3.connect(path)
    try:
        db.execute(f"PRAGMA user_version = {version}")
        db.commit()
    finally:
        db.close()


# Schema version --------------------------------------------------------------------------------


#: The jobs table of schema version 1, as gateways of that version (and before it) wrote it.
_VERSION_1_TABLE = """CREATE TABLE jobs (
    id TEXT PRIMARY KEY, kind TEXT NOT NULL, state TEXT NOT NULL,
    dataset TEXT NOT NULL, sequences TEXT NOT NULL, created REAL NOT NULL,
    total INTEGER NOT NULL DEFAULT 0, done INTEGER NOT NULL DEFAULT 0,
    failed INTEGER NOT NULL DEFAULT 0, errors TEXT NOT NULL DEFAULT '[]',
    reason TEXT, metrics TEXT, predictions TEXT, report TEXT,
    started REAL, finished REAL, attempts INTEGER NOT NULL DEFAULT 0)"""


def _old_database(path: Path, version: int, job_id: str) -> None:
    """A file of schema version 1, 2, 3 or 4 (stamped `version`: 0 is a file from before the
    version was kept) holding one running job with counts, started twice."""
    db = sqlite3.connect(path)
    try:
        db.execute(_VERSION_1_TABLE)
        db.execute("CREATE INDEX jobs_state ON jobs (state, created)")
        if version >= 2:
            db.execute("ALTER TABLE jobs ADD COLUMN submission INTEGER NOT NULL DEFAULT 0")
        if version >= 3:
            db.execute("ALTER TABLE jobs ADD COLUMN model TEXT")
        if version >= 4:
            db.execute("ALTER TABLE jobs ADD COLUMN version TEXT")
            db.execute("ALTER TABLE jobs ADD COLUMN split TEXT")
        db.execute(
            "INSERT INTO jobs (id, kind, state, dataset, sequences, created, total, done, "
            "attempts, started) VALUES (?, 'archive', 'running', '/data', '[\"11\"]', 1.0, 5, 3, "
            "2, 2.0)",
            (job_id,),
        )
        db.execute(f"PRAGMA user_version = {version}")
        db.commit()
    finally:
        db.close()


def _columns(path: Path) -> list[str]:
    db = sqlite3.connect(path)
    try:
        return [row[1] for row in db.execute("PRAGMA table_info(jobs)")]
    finally:
        db.close()


def test_a_new_database_is_stamped_with_the_schema_version(tmp_path):
    path = tmp_path / "state" / "jobs.sqlite"
    store = JobStore(path)
    store.create("a" * 32, "dataset", tmp_path, ["08"], model="panda")
    store.create("d" * 32, "dataset", tmp_path, ["scene-0103"], "nu", "v1.0-mini", "mini_val")
    store.create("e" * 32, "archive", tmp_path, ["08"], panoptic=True)
    store.close()
    assert _user_version(path) == SCHEMA_VERSION == 5
    assert _columns(path)[-6:] == [
        "attempts",
        "submission",
        "model",
        "version",
        "split",
        "panoptic",
    ]
    again = JobStore(path)
    try:
        record = again.get("a" * 32)
        assert record.state is JobState.queued and record.submission == 0
        assert (record.model, record.version, record.split) == ("panda", None, None)
        assert record.panoptic is False and record.selection(KITTI_LAYOUT).panoptic is False
        nuscenes = again.get("d" * 32)
        assert (nuscenes.model, nuscenes.version, nuscenes.split) == ("nu", "v1.0-mini", "mini_val")
        panoptic = again.get("e" * 32)
        assert panoptic.panoptic is True and panoptic.selection(KITTI_LAYOUT).panoptic is True
    finally:
        again.close()
    assert _user_version(path) == SCHEMA_VERSION


@pytest.mark.parametrize(
    "version",
    [0, 1, 2, 3, 4],
    ids=["before-versions", "version-1", "version-2", "version-3", "version-4"],
)
def test_an_older_database_is_migrated_and_keeps_its_jobs(tmp_path, version):
    path = tmp_path / "jobs.sqlite"
    _old_database(path, version, "b" * 32)
    reopened = JobStore(path)
    try:
        record = reopened.get("b" * 32)
        assert record.state is JobState.running and record.sequences == ["11"]
        assert (record.total, record.done, record.attempts, record.started) == (5, 3, 2, 2.0)
        assert record.submission == 0
        assert record.model is None  # from before models: the default model's
        assert (record.version, record.split) == (None, None)  # from before tables layouts
        assert record.panoptic is False  # from before panoptic jobs
        assert reopened.next_submission("b" * 32) == 1
    finally:
        reopened.close()
    assert _user_version(path) == SCHEMA_VERSION
    assert _columns(path)[-5:] == ["submission", "model", "version", "split", "panoptic"]
    again = JobStore(path)  # a migrated file opens as it is
    try:
        assert again.get("b" * 32).submission == 1
    finally:
        again.close()


def test_submissions_are_counted_and_kept_across_restarts(tmp_path):
    path = tmp_path / "jobs.sqlite"
    store = JobStore(path)
    store.create("c" * 32, "dataset", tmp_path, ["08"])
    assert [store.next_submission("c" * 32) for _ in range(3)] == [1, 2, 3]
    assert store.claim_next().submission == 3
    store.close()
    again = JobStore(path)
    try:
        assert again.get("c" * 32).submission == 3 and again.next_submission("c" * 32) == 4
        with pytest.raises(KeyError):
            again.next_submission("not-a-job")
    finally:
        again.close()


def test_a_newer_database_is_refused_naming_the_file_and_both_versions(tmp_path):
    path = tmp_path / "jobs.sqlite"
    JobStore(path).close()
    _set_user_version(path, SCHEMA_VERSION + 1)
    with pytest.raises(JobDatabaseVersionError) as caught:
        JobStore(path)
    message = str(caught.value)
    assert isinstance(caught.value, ValueError) and "\n" not in message
    assert str(path) in message
    assert f"version {SCHEMA_VERSION + 1}" in message and f"version {SCHEMA_VERSION}" in message
    assert _user_version(path) == SCHEMA_VERSION + 1  # left as it was


def test_create_app_refuses_a_newer_database_before_serving(tmp_path):
    settings = Settings(state_dir=tmp_path)
    JobStore(settings.database_path).close()
    _set_user_version(settings.database_path, SCHEMA_VERSION + 5)
    with pytest.raises(JobDatabaseVersionError, match=str(SCHEMA_VERSION + 5)):
        create_app(
            settings,
            FakeLabeller(),
            FakeExecutor(),
            models=one_model(load_profile("semantickitti")),
        )
    assert not (tmp_path / "absent").exists()
    create_app(
        Settings(state_dir=tmp_path / "absent"),
        FakeLabeller(),
        FakeExecutor(),
        models=one_model(load_profile("semantickitti")),
    )
    assert not (tmp_path / "absent").exists()  # checking creates nothing


# No SQLite on the event loop -------------------------------------------------------------------


class FakeLabeller:
    """A single-scan labeller answering label 40 for every point."""

    backend = "local"

    async def start(self, on_batch=None):
        return None

    async def stop(self):
        return None

    async def label_points(self, points, knn=True, confidence=False, panoptic=False, *, model):
        return ScanPrediction(np.full(len(points), 40, dtype=np.uint32))

    def depth(self):
        return 0

    def loaded(self):
        return ["default"]

    async def health(self):
        return {"backend": "local", "ok": True, "actors": [{"pid": os.getpid()}]}


class FakeExecutor:
    """Writes all-zero predictions of the right length."""

    backend = "fake"
    precision = "fp32"
    inference_backend = "torch"

    def predict(self, entries, dataset, sequences, out, progress, cancel, model=None):
        for i, entry in enumerate(entries):
            n = os.path.getsize(entry.scan_path) // 16
            write_labels(
                prediction_path(out, entry.sequence, entry.name), np.zeros(n, dtype=np.uint32)
            )
            progress(i + 1, 0, len(entries))
        return {}


def _loop_checked_store(on_loop: list[str]) -> type[JobStore]:
    """A `JobStore` whose every method records (and refuses) a call made on a running event loop."""

    def guarded(name: str, method):
        @functools.wraps(method)
        def call(self, *args, **kwargs):
            try:
                asyncio.get_running_loop()
            except RuntimeError:
                return method(self, *args, **kwargs)
            on_loop.append(f"{name} in {threading.current_thread().name}")
            raise AssertionError(f"JobStore.{name} was called on the event loop")

        return call

    methods = {
        name: guarded(name, value)
        for name, value in vars(JobStore).items()
        if callable(value) and (not name.startswith("__") or name == "__init__")
    }
    return type("LoopCheckedStore", (JobStore,), methods)


def _wait(client: TestClient, job_id: str) -> dict:
    deadline = time.time() + 30
    while time.time() < deadline:
        status = client.get(f"/v1/jobs/{job_id}").json()
        if status["state"] in ("succeeded", "failed", "cancelled"):
            return status
        time.sleep(0.05)
    raise AssertionError(f"job {job_id} did not finish: {status}")


def test_routes_never_touch_the_store_on_the_event_loop(tmp_path, monkeypatch):
    on_loop: list[str] = []
    monkeypatch.setattr("service.gateway.JobStore", _loop_checked_store(on_loop))
    roots = tmp_path / "roots"
    make_tree(roots / "data", {"08": [30, 40], "11": [20]}, labelled=True)
    settings = Settings(state_dir=tmp_path / "state", data_roots=[roots], api_token=TOKEN)
    app = create_app(
        settings, FakeLabeller(), FakeExecutor(), models=one_model(load_profile("semantickitti"))
    )
    archive = io.BytesIO()
    with zipfile.ZipFile(archive, "w") as zf:
        for path in sorted((roots / "data").rglob("*.bin")):
            zf.write(path, path.relative_to(roots / "data").as_posix())
    with TestClient(app, headers=AUTH) as client:
        assert client.get("/healthz").status_code == 200
        created = client.post("/v1/jobs", json={"dataset": "data", "sequences": ["08"]})
        uploaded = client.post(
            "/v1/jobs", files={"archive": ("data.zip", archive.getvalue(), "application/zip")}
        )
        assert created.status_code == 202 and uploaded.status_code == 202, (
            created.text,
            uploaded.text,
        )
        first, second = created.json()["id"], uploaded.json()["id"]
        assert _wait(client, first)["state"] == "succeeded"
        assert _wait(client, second)["state"] == "succeeded"
        assert {j["id"] for j in client.get("/v1/jobs").json()["jobs"]} == {first, second}
        assert client.get(f"/v1/jobs/{first}/predictions").status_code == 200
        assert client.get(f"/v1/jobs/{first}/report").json()["num_scans"] == 2
        assert client.get(f"/v1/jobs/{second}/report").status_code == 404  # no labels uploaded
        assert 'rangeret_jobs{state="succeeded"} 2.0' in client.get("/metrics").text
        assert client.delete(f"/v1/jobs/{first}").json()["state"] == "succeeded"
        assert client.get(f"/v1/jobs/{first}").status_code == 404
        assert client.delete(f"/v1/jobs/{first}").status_code == 404
        assert client.get(f"/v1/jobs/{first}/predictions").status_code == 404
        scan = np.ones((7, 4), dtype=np.float32).tobytes()
        labelled = client.post(
            "/v1/scans", content=scan, headers={"Content-Type": "application/octet-stream"}
        )
        assert labelled.content == np.full(7, 40, dtype="<u4").tobytes()
    assert on_loop == []


# Claims ----------------------------------------------------------------------------------------


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
