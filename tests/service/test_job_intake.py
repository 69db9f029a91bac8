"""A new job's intake on its own (`service.jobs.intake`), without a server: the dataset a request
names, the checks before an upload is read, extraction into the job's folder, and the folder
removed again whenever a job is not queued."""

from __future__ import annotations

import asyncio
import errno
import zipfile
from pathlib import Path

import numpy as np
import pytest

from rangeret.dataset.profiles import load_profile
from service.http.errors import ApiError
from service.jobs import JobManager, JobStore
from service.jobs.intake import JobIntake, resolve_dataset
from service.routes.job_errors import REFUSALS, job_error_answer
from service.schemas import DatasetJobRequest, JobState
from service.settings import Settings
from tests.support.apps import one_model
from tests.support.jobs import FakeExecutor
from tests.support.trees import make_tree

KITTI = load_profile(None)
MODEL = one_model(KITTI).default_entry
SCAN = np.arange(40, dtype=np.float32).reshape(10, 4).tobytes()


@pytest.fixture
def roots(tmp_path: Path) -> Path:
    roots = tmp_path / "roots"
    make_tree(roots / "data", {"08": [30, 40], "11": [20]})
    return roots


def _intake(tmp_path: Path, roots: Path, **limits) -> JobIntake:
    """An intake for a manager that is not started, so its jobs stay queued."""
    settings = Settings(state_dir=tmp_path / "state", data_roots=[roots])
    manager = JobManager(
        JobStore(tmp_path / "jobs.sqlite"),
        FakeExecutor(),
        tmp_path / "jobs",
        3600,
        models=one_model(KITTI),
        **limits,
    )
    return JobIntake(manager, settings, one_model(KITTI))


def _job_folders(intake: JobIntake) -> list[str]:
    jobs_dir = intake.jobs.jobs_dir
    return sorted(p.name for p in jobs_dir.iterdir()) if jobs_dir.is_dir() else []


def _refusal(call, *args) -> ApiError:
    """The answer the routes give to what `call` refuses with."""
    with pytest.raises(REFUSALS) as refused:
        call(*args)
    return job_error_answer(refused.value)


def _zip_into(path: Path, members: dict[str, bytes]) -> None:
    with zipfile.ZipFile(path, "w") as zf:
        for name, data in members.items():
            zf.writestr(name, data)


# The dataset a request names -------------------------------------------------------------------


def test_a_dataset_is_found_under_the_roots_and_refused_elsewhere(tmp_path, roots):
    found = roots / "data"
    assert resolve_dataset("data", [roots]) == found
    assert resolve_dataset(str(found), [roots]) == found
    assert _refusal(resolve_dataset, "data", []).status_code == 403
    outside = _refusal(resolve_dataset, str(tmp_path), [roots])
    assert (outside.status_code, outside.detail) == (
        403,
        "The dataset path is outside the configured data roots.",
    )
    assert _refusal(resolve_dataset, "absent", [roots]).status_code == 404
    assert _refusal(resolve_dataset, "data\0", [roots]).status_code == 400


def test_a_dataset_request_gives_the_scans_of_its_sequences(tmp_path, roots):
    intake = _intake(tmp_path, roots)
    found = intake.dataset_input(DatasetJobRequest(dataset="data", sequences=["08"]), MODEL)
    assert found.root == roots / "data" and found.sequences == ["08"]
    assert [e.key for e in found.entries] == ["08/000000", "08/000001"]
    assert (found.version, found.split) == (None, None)


def test_a_dataset_request_for_another_profile_or_unusable_sequences_is_400(tmp_path, roots):
    intake = _intake(tmp_path, roots)
    other = _refusal(
        intake.dataset_input,
        DatasetJobRequest(dataset="data", split="valid", profile="pandaset"),
        MODEL,
    )
    assert other.status_code == 400 and "'pandaset'" in other.detail
    assert "'semantickitti'" in other.detail
    absent = _refusal(
        intake.dataset_input, DatasetJobRequest(dataset="data", sequences=["09"]), MODEL
    )
    assert absent.status_code == 400 and absent.detail.startswith("The dataset cannot be used: ")
    assert _job_folders(intake) == []


def test_a_dataset_whose_scans_link_out_of_the_roots_is_403(tmp_path, roots):
    outside = tmp_path / "outside.bin"
    outside.write_bytes(SCAN)
    scan = roots / "data" / "sequences" / "08" / "velodyne" / "000001.bin"
    scan.unlink()
    scan.symlink_to(outside)
    refused = _refusal(
        _intake(tmp_path, roots).dataset_input,
        DatasetJobRequest(dataset="data", sequences=["08"]),
        MODEL,
    )
    assert refused.status_code == 403 and "(the first: 08/000001)" in refused.detail
    assert str(tmp_path) not in refused.detail


def test_a_dataset_job_is_queued_with_its_folder(tmp_path, roots):
    intake = _intake(tmp_path, roots)
    record = asyncio.run(intake.dataset_job(DatasetJobRequest(dataset="data", split="valid")))
    assert (record.kind, record.state, record.sequences) == ("dataset", JobState.queued, ["08"])
    assert _job_folders(intake) == [record.id]
    assert (intake.jobs.job_dir(record.id) / "profile.txt").read_text() == "semantickitti\n"


def test_a_dataset_job_that_does_not_fit_leaves_no_folder(tmp_path, roots):
    intake = _intake(tmp_path, roots, max_bytes=100)
    request = DatasetJobRequest(dataset="data", sequences=["08"])
    refused = _refusal(asyncio.run, intake.dataset_job(request))
    assert refused.status_code == 507 and "RANGERET_MAX_JOB_BYTES" in refused.detail
    assert _job_folders(intake) == [] and intake.jobs.store.list() == []


# Before an upload is read ----------------------------------------------------------------------


def test_a_full_queue_is_429_and_an_upload_that_cannot_fit_is_507(tmp_path, roots):
    intake = _intake(tmp_path, roots, max_queued=1)
    intake.check_queue()
    asyncio.run(intake.dataset_job(DatasetJobRequest(dataset="data", sequences=["11"])))
    full = _refusal(intake.check_queue)
    assert full.status_code == 429 and "RANGERET_MAX_QUEUED_JOBS" in full.detail
    intake.check_upload(None)
    intake.check_upload(1 << 20)
    too_big = _refusal(intake.check_upload, intake.settings.max_job_bytes)
    assert too_big.status_code == 507 and "RANGERET_MAX_JOB_BYTES" in too_big.detail


# Uploads ---------------------------------------------------------------------------------------


def test_an_upload_is_extracted_into_the_job_folder_and_removed(tmp_path, roots):
    intake = _intake(tmp_path, roots)
    folder = tmp_path / "job"
    folder.mkdir()
    upload = folder / "upload.part"
    _zip_into(upload, {"sequences/08/velodyne/000000.bin": SCAN})
    found = intake.extract_upload(upload, folder, MODEL)
    assert found.root == folder / "data" and found.sequences == ["08"]
    assert len(found.entries) == 1 and found.version is None
    assert not upload.exists()
    _zip_into(upload, {"sequences/08/velodyne/000000.bin": SCAN[:-4]})
    refused = _refusal(intake.extract_upload, upload, folder, MODEL)
    assert refused.status_code == 400 and not upload.exists()


def test_an_archive_job_is_received_extracted_and_queued(tmp_path, roots):
    intake = _intake(tmp_path, roots)

    async def receive(path: Path) -> None:
        _zip_into(path, {"sequences/11/velodyne/000000.bin": SCAN})

    record = asyncio.run(intake.archive_job(receive, MODEL))
    folder = intake.jobs.job_dir(record.id)
    assert (record.kind, record.state, record.sequences) == ("archive", JobState.queued, ["11"])
    assert Path(record.dataset) == folder / "data"
    assert (folder / "data" / "sequences" / "11" / "velodyne" / "000000.bin").read_bytes() == SCAN
    assert not (folder / "upload.part").exists()


def test_an_upload_cut_short_or_on_a_full_disk_leaves_no_folder(tmp_path, roots):
    intake = _intake(tmp_path, roots)

    async def too_slow(path: Path) -> None:
        path.write_bytes(b"PK")
        raise ApiError(408, "The archive did not arrive in time.")

    async def disk_full(path: Path) -> None:
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    async def broken(path: Path) -> None:
        raise OSError(errno.EIO, "Input/output error", str(path))

    with pytest.raises(ApiError) as slow:
        asyncio.run(intake.archive_job(too_slow, MODEL))
    assert slow.value.status_code == 408
    full = _refusal(asyncio.run, intake.archive_job(disk_full, MODEL))
    assert full.status_code == 507
    assert full.detail == (
        f"Insufficient storage: the disk of the jobs folder {intake.jobs.jobs_dir} is full; "
        "free space there, or upload a smaller archive."
    )
    with pytest.raises(OSError) as other:
        asyncio.run(intake.archive_job(broken, MODEL))
    assert other.value.errno == errno.EIO
    assert _job_folders(intake) == [] and intake.jobs.store.list() == []
