"""A claimed job's work on its own (`service.jobs.work.JobWork`), without runner threads: the
results and final record it writes, and each way it fails or stops."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import pytest

from rangeret.dataset.profiles import load_profile
from service.jobs import JobControl, JobStore, JobWork
from service.jobs.work import PROFILE_FILE, accepted_profile
from service.models.catalog import ModelCatalog
from service.schemas import JobState
from tests.support.apps import one_model
from tests.support.jobs import FakeExecutor
from tests.support.trees import make_tree

KITTI = load_profile(None)


@pytest.fixture
def store(tmp_path: Path):
    store = JobStore(tmp_path / "jobs.sqlite")
    yield store
    store.close()


def _claimed(store: JobStore, tmp_path: Path, data: Path, sequences: list[str]):
    """A running job over `sequences` of `data` and its (empty) folder."""
    folder = tmp_path / "jobs" / "job1"
    folder.mkdir(parents=True)
    store.create("job1", "dataset", data, sequences)
    store.start("job1")
    return store.get("job1"), folder


class FailingExecutor(FakeExecutor):
    """Writes every prediction but reports the first scan as failed, naming a server path."""

    def predict(self, entries, dataset, sequences, out, progress, cancel, model=None):
        super().predict(entries, dataset, sequences, out, progress, cancel)
        return {entries[0].key: f"cannot read {out}/x.label: [Errno 5] Input/output error"}


class SilentExecutor(FakeExecutor):
    """Reports success and writes nothing."""

    def predict(self, entries, dataset, sequences, out, progress, cancel, model=None):
        return {}


class StoppingExecutor(FakeExecutor):
    """Sets the job's control, as a cancel or a gateway stop does, then returns."""

    def predict(self, entries, dataset, sequences, out, progress, cancel, model=None):
        cancel.set()
        return {}


def test_a_labelled_job_succeeds_with_its_zip_report_plots_and_metrics(store, tmp_path):
    data = tmp_path / "data"
    make_tree(data, {"08": [30, 40], "11": [20]})
    job, folder = _claimed(store, tmp_path, data, ["08", "11"])
    counted: list[int] = []
    work = JobWork(
        store,
        FakeExecutor(),
        one_model(KITTI, "ab" * 32),
        on_scans=lambda n, model: counted.append(n),
    )
    assert work.run(job, folder, JobControl(job.id, store)) is True
    record = store.get(job.id)
    assert record.state is JobState.succeeded and (record.total, record.done) == (3, 3)
    assert sum(counted) == 3
    assert Path(record.predictions) == folder / "predictions.zip"
    with zipfile.ZipFile(record.predictions) as zf:
        assert "sequences/11/predictions/000000.label" in zf.namelist()
        assert "ab" * 32 in zf.read("description.txt").decode()
    report = json.loads(Path(record.report).read_text())
    assert report["sequences"] == ["08", "11"] and report["num_scans"] == 3
    assert (report["precision"], report["backend"]) == ("fp32", "torch")
    assert set(record.metrics) == {"miou", "accuracy", "iou"}
    assert any((folder / "plots").glob("*.png"))


def test_an_unlabelled_job_succeeds_without_a_report(store, tmp_path):
    data = tmp_path / "data"
    make_tree(data, {"08": [30]}, labelled=False)
    job, folder = _claimed(store, tmp_path, data, ["08"])
    assert JobWork(store, FakeExecutor(), one_model(KITTI)).run(
        job, folder, JobControl(job.id, store)
    )
    record = store.get(job.id)
    assert record.state is JobState.succeeded and record.report is None
    assert record.metrics is None and Path(record.predictions).is_file()
    assert not (folder / "plots").exists()


def test_a_job_stopped_while_it_predicts_is_left_without_a_final_record(store, tmp_path):
    data = tmp_path / "data"
    make_tree(data, {"08": [30]}, labelled=False)
    job, folder = _claimed(store, tmp_path, data, ["08"])
    control = JobControl(job.id, store)
    assert JobWork(store, StoppingExecutor(), one_model(KITTI)).run(job, folder, control) is False
    assert control.is_set() and store.get(job.id).state is JobState.running
    assert not (folder / "predictions.zip").exists()


def test_failed_scans_fail_the_job_with_errors_free_of_server_paths(store, tmp_path):
    data = tmp_path / "data"
    make_tree(data, {"08": [30, 40]}, labelled=False)
    job, folder = _claimed(store, tmp_path, data, ["08"])
    assert JobWork(store, FailingExecutor(), one_model(KITTI)).run(
        job, folder, JobControl(job.id, store)
    )
    record = store.get(job.id)
    assert record.state is JobState.failed
    assert record.reason == "1 of 2 scans could not be predicted (see errors)"
    assert record.errors == ["08/000000: cannot read predictions/x.label: Input/output error"]


def test_predictions_missing_once_written_fail_the_job_naming_them(store, tmp_path):
    data = tmp_path / "data"
    make_tree(data, {"08": [30, 40]}, labelled=False)
    job, folder = _claimed(store, tmp_path, data, ["08"])
    assert JobWork(store, SilentExecutor(), one_model(KITTI)).run(
        job, folder, JobControl(job.id, store)
    )
    record = store.get(job.id)
    assert record.state is JobState.failed and record.done == 0
    assert record.reason.startswith("2 of 2 predictions are missing from the job's folder")
    assert "predictions/sequences/08/predictions/000000.label" in record.reason
    assert str(tmp_path) not in record.reason


def test_a_job_accepted_for_another_profile_is_not_read(store, tmp_path):
    data = tmp_path / "data"
    make_tree(data, {"08": [30]}, labelled=False)
    job, folder = _claimed(store, tmp_path, data, ["08"])
    (folder / PROFILE_FILE).write_text("pandaset\n")
    assert accepted_profile(folder) == "pandaset"
    assert JobWork(store, FakeExecutor(), one_model(KITTI)).run(
        job, folder, JobControl(job.id, store)
    )
    record = store.get(job.id)
    assert record.state is JobState.failed
    assert record.reason == (
        "the job was accepted for the pandaset profile, and its model now runs with the "
        "semantickitti profile"
    )
    assert not (folder / "predictions").exists()


def test_a_folder_without_a_profile_file_is_read_in_the_served_profile(store, tmp_path):
    data = tmp_path / "data"
    make_tree(data, {"08": [30]}, labelled=False)
    job, folder = _claimed(store, tmp_path, data, ["08"])
    assert accepted_profile(folder) is None
    assert JobWork(store, FakeExecutor(), one_model(KITTI)).run(
        job, folder, JobControl(job.id, store)
    )
    assert store.get(job.id).state is JobState.succeeded


def test_scans_outside_the_read_roots_fail_the_job_before_it_predicts(store, tmp_path):
    data = tmp_path / "data"
    make_tree(data, {"08": [30]}, labelled=False)
    job, folder = _claimed(store, tmp_path, data, ["08"])
    executor = FakeExecutor()
    work = JobWork(
        store, executor, one_model(KITTI), read_roots=[(tmp_path / "elsewhere").resolve()]
    )
    assert work.run(job, folder, JobControl(job.id, store))
    record = store.get(job.id)
    assert record.state is JobState.failed and "outside the data roots" in record.reason
    assert record.reason.startswith("The job has 1 scan(s)") and not executor.started.is_set()


def test_the_local_executor_records_each_job_run_in_run_json(store, tmp_path):
    """The gateway's in-process jobs write run.json like every runner."""
    from rangeret.inference.predictor import Predictor
    from rangeret.inference.scan_worker import ScanWorker
    from rangeret.inference.spec import InferenceSpec
    from rangeret.io.run_info import read_run_info
    from service.jobs.executors import LocalExecutor
    from tests.support.apps import pooled
    from tests.support.workers import build_tree, small_weights

    data = build_tree(tmp_path / "data", labelled=1, unlabelled=1)
    job, folder = _claimed(store, tmp_path, data, ["08", "11"])
    spec = InferenceSpec(
        checkpoint=str(small_weights(tmp_path)), height=32, width=256, device="cpu"
    )
    predictor = Predictor.from_spec(spec)
    executor = LocalExecutor(pooled(ScanWorker(predictor)).pool, "default")
    work = JobWork(store, executor, one_model(KITTI))
    assert work.run(job, folder, JobControl(job.id, store)) is True
    assert store.get(job.id).state is JobState.succeeded
    record = read_run_info(folder / "predictions")
    assert record["runner"] == "service job" and record["sequences"] == ["08", "11"]
    assert [r["runner"] for r in record["runs"]] == ["service job"]
    assert len(record["checkpoint_sha256"]) == 64


def test_a_job_whose_model_is_no_longer_served_fails_naming_it(store, tmp_path):
    data = tmp_path / "data"
    make_tree(data, {"08": [30]}, labelled=False)
    folder = tmp_path / "jobs" / "job2"
    folder.mkdir(parents=True)
    store.create("job2", "dataset", data, ["08"], model="retired")
    store.start("job2")
    job = store.get("job2")
    models = one_model(KITTI, name="kitti")
    assert JobWork(store, FakeExecutor(), models).run(job, folder, JobControl(job.id, store))
    record = store.get(job.id)
    assert record.state is JobState.failed
    assert (
        record.reason == "the job's model retired is no longer served (this gateway serves kitti)"
    )
    assert not (folder / "predictions").exists()


def test_each_job_runs_with_its_own_model(store, tmp_path):
    """The executor is told the job's model; a job from before models gets the default one."""
    data = tmp_path / "data"
    make_tree(data, {"08": [30]}, labelled=False)
    seen = []

    class Recording(FakeExecutor):
        def predict(self, entries, dataset, sequences, out, progress, cancel, model=None):
            seen.append(model)
            return super().predict(entries, dataset, sequences, out, progress, cancel)

    panda = one_model(load_profile("pandaset"), name="panda").default_entry
    kitti = one_model(KITTI, name="kitti").default_entry
    models = ModelCatalog({"kitti": kitti, "panda": panda}, "kitti")
    for job_id, model in (("j1", None), ("j2", "kitti")):
        folder = tmp_path / "jobs" / job_id
        folder.mkdir(parents=True)
        store.create(job_id, "dataset", data, ["08"], model=model)
        store.start(job_id)
        JobWork(store, Recording(), models).run(
            store.get(job_id), folder, JobControl(job_id, store)
        )
        assert store.get(job_id).state is JobState.succeeded
    assert seen == ["kitti", "kitti"]
