"""Gateway jobs as Ray jobs (`service.jobs.ray_jobs`) and the progress record they keep.

Without Ray: the progress record (`workers.progress`), the finished/died decision, and the
executor's whole life cycle against a scripted Jobs API (submission, re-submission after a death,
the limit, re-attaching, a Jobs API that does not answer, cancel versus a gateway stop).

With Ray (slow): a real `ray start --head` with token authentication and a real gateway process
given RANGERET_JOBS_ADDRESS. Its jobs' labels equal `rangeret predict`'s and their reports
`rangeret evaluate`'s; a cancel stops the Ray job; a gateway killed or stopped mid-job finds its
Ray job again; a Ray job stopped behind the gateway's back is submitted again and none of its
scans is written twice; a scan that cannot be read fails the job, naming it; a wrong Ray token is
one sentence naming the address.
"""

from __future__ import annotations

import io
import json
import os
import shlex
import signal
import subprocess
import sys
import threading
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path

import pytest

from rangeret.cli.main import main as rangeret_main
from rangeret.dataset.layout import KITTI_LAYOUT, list_scans, velodyne_dir
from rangeret.dataset.profiles import load_profile
from rangeret.dataset.selection import DatasetSelection
from rangeret.inference.spec import InferenceSpec
from service.jobs import JobControl, JobError, JobManager, JobStore
from service.jobs.jobs_api import JobsApi, JobsApiError, JobsApiUnreachable
from service.jobs.ray_jobs import RayJobExecutor, Verdict, submission_id, verdict
from service.models.catalog import ModelCatalog, ModelEntry
from service.schemas import JobState
from tests.support.apps import one_model
from tests.support.gateway import Gateway, gateway_env, start_gateway, wait_job
from tests.support.paths import REPO
from tests.support.trees import make_tree
from tests.support.workers import build_tree, ray_node, small_weights, tree_bytes
from workers.progress import (
    PROGRESS_FILE,
    JobProgress,
    ProgressWriter,
    progress_path,
    read_progress,
    write_progress,
)

# The progress record ------------------------------------------------------------------------


def test_a_progress_record_reads_back_as_written_and_a_bad_one_as_none(tmp_path):
    assert read_progress(tmp_path) is None  # none yet
    record = JobProgress(
        total=5, done=4, failed=1, failures={"08/000001": "truncated"}, finished=True
    )
    write_progress(tmp_path, record)
    assert progress_path(tmp_path) == tmp_path / PROGRESS_FILE
    assert read_progress(tmp_path) == record
    assert [p.name for p in tmp_path.iterdir()] == [PROGRESS_FILE]  # no temporary file left
    for text in ("", "{", "[]", '{"total": -1}', '{"done": "3"}', '{"failures": {"a": 1}}',
                 '{"finished": "yes"}', '{"error": 3}'):  # fmt: skip
        progress_path(tmp_path).write_text(text)
        assert read_progress(tmp_path) is None, text
    progress_path(tmp_path).write_text('{"total": 2, "done": 1, "later": true}')
    assert read_progress(tmp_path) == JobProgress(total=2, done=1)  # unknown keys are ignored


def test_the_writer_records_the_start_batches_at_most_once_a_second_and_the_end(tmp_path):
    now = [100.0]
    writer = ProgressWriter(tmp_path, clock=lambda: now[0])
    writer.start(total=10, done=4)
    assert read_progress(tmp_path) == JobProgress(total=10, done=4)
    now[0] += 0.5
    writer.batch(2, 0, 6)
    assert read_progress(tmp_path).done == 4  # too soon after the last record
    now[0] += 0.6
    writer.batch(3, 1, 6)
    assert (read_progress(tmp_path).done, read_progress(tmp_path).failed) == (6, 1)
    writer.batch(6, 1, 6)  # the last batch is always written
    assert (read_progress(tmp_path).done, read_progress(tmp_path).failed) == (9, 1)
    assert not writer.finished and not read_progress(tmp_path).finished
    writer.finish(failures={"11/000007": "bad scan"}, precision="fp32")
    final = read_progress(tmp_path)
    assert writer.finished and final.finished and final.error is None
    assert (final.total, final.done, final.failed) == (10, 9, 1)
    assert final.failures == {"11/000007": "bad scan"} and final.precision == "fp32"


def test_the_final_record_of_a_job_stopped_on_bad_input_holds_one_sentence(tmp_path):
    writer = ProgressWriter(tmp_path)
    writer.finish(error="the dataset has no sequence 99:\n  check --sequences")
    final = read_progress(tmp_path)
    assert final.finished and final.error == "the dataset has no sequence 99: check --sequences"
    assert final.total == 0 and final.failures == {}


def test_predict_job_writes_a_final_record_when_its_input_is_bad(tmp_path):
    """The job stops on a CommandError before it joins a cluster, and says why in the record of
    its output folder (which the gateway makes before it submits); without that folder, the
    refused job leaves none behind."""
    out = tmp_path / "pred"
    out.mkdir()
    data = build_tree(tmp_path / "data", labelled=1, unlabelled=0)
    weights = small_weights(tmp_path)
    cmd = [sys.executable, "-m", "workers.predict_job", "--dataset", str(data)]
    cmd += ["--sequences", "08", "42", "--out", str(out), "--checkpoint", str(weights)]
    cmd += ["--height", "32", "--width", "256", "--device", "cpu"]
    run = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=120, check=False)
    assert run.returncode == 1 and "Traceback" not in run.stderr, run.stderr
    final = read_progress(out)
    assert final is not None and final.finished, run.stderr
    assert "42" in final.error and final.error in run.stderr.replace("\n", " ")
    cmd[cmd.index(str(out))] = str(tmp_path / "absent")
    run = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=120, check=False)
    assert run.returncode == 1 and not (tmp_path / "absent").exists(), run.stderr


# The finished/died decision -----------------------------------------------------------------

_FINAL = JobProgress(total=3, done=3, finished=True)
_FAILED_SCANS = JobProgress(total=3, done=2, failed=1, failures={"08/000001": "x"}, finished=True)
_SO_FAR = JobProgress(total=3, done=1)


@pytest.mark.parametrize(
    ("status", "record", "expected"),
    [
        ("PENDING", None, Verdict.running),
        ("RUNNING", None, Verdict.running),
        ("RUNNING", _SO_FAR, Verdict.running),
        ("RUNNING", _FINAL, Verdict.finished),  # the record is written just before it exits
        ("SUCCEEDED", _FINAL, Verdict.finished),
        ("FAILED", _FAILED_SCANS, Verdict.finished),  # exit 1 for failed scans
        (None, _FINAL, Verdict.finished),  # finished, and forgotten by the cluster since
        ("SUCCEEDED", None, Verdict.died),
        ("FAILED", _SO_FAR, Verdict.died),
        ("STOPPED", _SO_FAR, Verdict.died),
        ("STOPPED", None, Verdict.died),
        (None, None, Verdict.died),  # the Jobs API no longer knows the submission
        (None, _SO_FAR, Verdict.died),
    ],
)
def test_a_job_is_finished_by_its_final_record_and_died_when_it_ended_without_one(
    status, record, expected
):
    assert verdict(status, record) is expected


# The executor against a scripted Jobs API ---------------------------------------------------

JOB = "f" * 32
ADDRESS = "http://ray-head.example:8265"


class ScriptedApi:
    """A Jobs API in memory: statuses by submission id, and hooks run on each submission."""

    address = ADDRESS

    def __init__(self, on_submit=None) -> None:
        self.statuses: dict[str, str] = {}
        self.submitted: list[tuple[str, str]] = []
        self.stopped: list[str] = []
        self.down = False
        self.refuse: str | None = None
        self.on_submit = on_submit or (lambda api, sid, n: None)

    def status(self, sid: str) -> str | None:
        if self.down:
            raise JobsApiUnreachable(f"the Ray Jobs API at {ADDRESS} does not answer (refused)")
        return self.statuses.get(sid)

    def submit(self, sid: str, entrypoint: str, metadata: dict[str, str]) -> None:
        if self.down:
            raise JobsApiUnreachable(f"the Ray Jobs API at {ADDRESS} does not answer (refused)")
        if self.refuse:
            raise JobsApiError(self.refuse)
        assert sid not in self.statuses, f"{sid} submitted twice"
        assert metadata == {"rangeret_job": JOB}
        self.statuses[sid] = "RUNNING"
        self.submitted.append((sid, entrypoint))
        self.on_submit(self, sid, len(self.submitted))

    def stop(self, sid: str) -> bool:
        self.stopped.append(sid)
        running = self.statuses.get(sid) in ("PENDING", "RUNNING")
        if running:
            self.statuses[sid] = "STOPPED"
        return running

    def log_tail(self, sid: str) -> str:
        return (
            'File "/opt/venv/lib/python3.12/site-packages/workers/predict_job.py", line 9 | '
            "--read-roots /srv/data /results/gateway/jobs | RuntimeError: the node went away"
        )


@dataclass
class Setup:
    store: JobStore
    control: JobControl
    executor: RayJobExecutor
    entries: list
    data: Path
    out: Path
    calls: list


def _models(spec: InferenceSpec) -> ModelCatalog:
    """The gateway's one model `default`, running `spec` with SemanticKITTI's profile."""
    return ModelCatalog.one(ModelEntry("default", spec, load_profile(None)))


def _setup(tmp_path: Path, api: ScriptedApi, **options) -> Setup:
    data = tmp_path / "data"
    make_tree(data, {"08": [30, 40], "11": [50]}, labelled=False)
    store = JobStore(tmp_path / "jobs.sqlite")
    store.create(JOB, "dataset", data, ["08", "11"])
    store.claim_next()
    spec = InferenceSpec(checkpoint="weights.pt", height=32, width=256, device="cpu", batch_size=2)
    options = {"poll_s": 0.01, "unreachable_s": 0.3, **options}
    executor = RayJobExecutor(ADDRESS, _models(spec), api=api, **options)
    entries = list_scans(data, ["08", "11"], layout=KITTI_LAYOUT)
    return Setup(store, JobControl(JOB, store), executor, entries, data, tmp_path / "out", calls=[])


def _predict(s: Setup) -> dict[str, str]:
    return s.executor.predict(
        s.entries, s.data, ["08", "11"], s.out, lambda *c: s.calls.append(c), s.control
    )


def _finish(out: Path, **fields) -> None:
    write_progress(out, JobProgress(total=3, done=3, finished=True, **fields))


def test_a_job_is_submitted_once_as_its_id_and_1_and_finishes_with_its_final_record(tmp_path):
    def run(api, sid, n):
        write_progress(setup.out, JobProgress(total=3, done=2))
        _finish(setup.out, precision="fp32")
        api.statuses[sid] = "SUCCEEDED"

    api = ScriptedApi(run)
    setup = _setup(tmp_path, api)
    assert _predict(setup) == {}
    assert [sid for sid, _ in api.submitted] == [submission_id(JOB, 1)] == [f"{JOB}-1"]
    assert setup.store.get(JOB).submission == 1
    entrypoint = api.submitted[0][1]
    assert entrypoint.startswith("python -m workers.predict_job --dataset ")
    assert f"--sequences 08 11 --out {setup.out}" in entrypoint
    argv = shlex.split(entrypoint)
    spec = json.loads(argv[argv.index("--inference-spec") + 1])
    assert spec == {
        "batch_size": 2,
        "checkpoint": "weights.pt",  # a name, resolved where the job runs
        "device": "cpu",
        "height": 32,
        "width": 256,
    }
    assert "--submission" not in entrypoint and "--report" not in entrypoint
    assert setup.calls[-1] == (3, 0, 3)  # every scan written, none failed, of 3 to predict
    assert setup.executor.precision == "fp32" and setup.executor.inference_backend == "torch"


def test_failed_scans_in_the_final_record_are_the_jobs_failures(tmp_path):
    def run(api, sid, n):
        _finish(setup.out, failed=1, failures={"11/000000": "truncated scan"})
        api.statuses[sid] = "FAILED"

    setup = _setup(tmp_path, ScriptedApi(run))
    assert _predict(setup) == {"11/000000": "truncated scan"}


def test_a_final_record_with_an_error_fails_the_job_with_its_sentence(tmp_path):
    def run(api, sid, n):
        _finish(setup.out, error="the dataset has no sequence 11")
        api.statuses[sid] = "FAILED"

    setup = _setup(tmp_path, ScriptedApi(run))
    with pytest.raises(JobError, match=f"no sequence 11 \\(Ray job {JOB}-1\\)"):
        _predict(setup)


def test_a_job_that_died_is_submitted_again_and_a_stale_record_is_removed_first(tmp_path):
    def run(api, sid, n):
        if n == 1:
            write_progress(setup.out, JobProgress(total=3, done=1))
            api.statuses[sid] = "STOPPED"
        else:
            assert read_progress(setup.out) is None  # attempt 1's record is gone
            _finish(setup.out)
            api.statuses[sid] = "SUCCEEDED"

    api = ScriptedApi(run)
    setup = _setup(tmp_path, api)
    assert _predict(setup) == {}
    assert [sid for sid, _ in api.submitted] == [f"{JOB}-1", f"{JOB}-2"]
    assert setup.store.get(JOB).submission == 2 and api.stopped == []


def test_a_job_that_dies_every_time_fails_naming_its_last_ray_job(tmp_path):
    def run(api, sid, n):
        api.statuses[sid] = "FAILED"

    api = ScriptedApi(run)
    setup = _setup(tmp_path, api)
    with pytest.raises(JobError) as caught:
        _predict(setup)
    message = str(caught.value)
    assert f"Ray job {JOB}-3 ended FAILED without finishing" in message
    assert "after 3 submissions" in message and "the node went away" in message
    # The log's tail names no server folder, only the files' own names.
    assert "/opt" not in message and "/srv" not in message and "/results" not in message
    assert 'File "…/predict_job.py"' in message and "--read-roots …/data …/jobs" in message
    assert "\n" not in message and len(api.submitted) == 3


def test_a_stored_submission_that_still_runs_is_followed_again_not_submitted(tmp_path):
    api = ScriptedApi()
    setup = _setup(tmp_path, api)
    setup.store.next_submission(JOB)
    api.statuses[f"{JOB}-1"] = "RUNNING"
    write_progress(setup.out, JobProgress(total=3, done=1))

    def finish_later():
        time.sleep(0.2)
        _finish(setup.out)
        api.statuses[f"{JOB}-1"] = "SUCCEEDED"

    threading.Thread(target=finish_later).start()
    assert _predict(setup) == {}
    assert api.submitted == [] and setup.store.get(JOB).submission == 1
    assert setup.calls[0] == (1, 0, 3) and setup.calls[-1] == (3, 0, 3)


def test_a_stored_submission_the_cluster_forgot_is_submitted_again(tmp_path):
    def run(api, sid, n):
        _finish(setup.out)

    api = ScriptedApi(run)
    setup = _setup(tmp_path, api)
    setup.store.next_submission(JOB)  # stored, and unknown to the Jobs API
    assert _predict(setup) == {}
    assert [sid for sid, _ in api.submitted] == [f"{JOB}-2"]


def test_a_jobs_api_that_is_briefly_silent_is_a_pause_and_a_long_silence_a_failure(tmp_path):
    def run(api, sid, n):
        api.down = True

    api = ScriptedApi(run)
    setup = _setup(tmp_path, api, unreachable_s=5.0)

    def come_back():
        time.sleep(0.3)
        api.down = False
        time.sleep(0.1)
        _finish(setup.out)

    threading.Thread(target=come_back).start()
    assert _predict(setup) == {} and len(api.submitted) == 1

    api = ScriptedApi(run)
    setup = _setup(tmp_path / "long", api, unreachable_s=0.2)
    with pytest.raises(JobError) as caught:
        _predict(setup)
    assert ADDRESS in str(caught.value) and "does not answer" in str(caught.value)
    assert "for 0.2 s" in str(caught.value) and f"{JOB}-1" in str(caught.value)


def test_a_job_finishes_while_the_jobs_api_is_silent(tmp_path):
    def run(api, sid, n):
        api.down = True
        _finish(setup.out)

    setup = _setup(tmp_path, ScriptedApi(run), unreachable_s=60)
    assert _predict(setup) == {}


def test_a_cancel_stops_the_ray_job_and_a_gateway_stop_leaves_it_running(tmp_path):
    def run(api, sid, n):
        threading.Timer(0.1, stop).start()

    api = ScriptedApi(run)
    setup = _setup(tmp_path, api)

    def stop():
        setup.control.set()  # the gateway stops: the job stays running in the store

    assert _predict(setup) == {}
    assert api.stopped == [] and api.statuses[f"{JOB}-1"] == "RUNNING"

    setup.control.clear()
    setup.store.requeue(JOB)
    setup.store.claim_next()

    def cancel():
        assert setup.store.cancel(JOB)
        setup.control.set()

    threading.Timer(0.1, cancel).start()
    assert _predict(setup) == {}  # the stored submission, followed again, then stopped
    assert len(api.submitted) == 1 and api.stopped == [f"{JOB}-1"]
    assert api.statuses[f"{JOB}-1"] == "STOPPED"


def test_a_refused_submission_fails_the_job_with_the_reason(tmp_path):
    api = ScriptedApi()
    api.refuse = f"the Ray Jobs API at {ADDRESS} refused the gateway's Ray token (403)"
    setup = _setup(tmp_path, api)
    with pytest.raises(JobError, match=r"could not be submitted: the Ray Jobs API at \S+ refused"):
        _predict(setup)
    assert setup.store.get(JOB).submission == 1  # counted before it was tried


def test_a_jobs_api_that_is_not_there_fails_the_job_naming_the_address(tmp_path):
    from tests.support.workers import free_ports

    address = f"http://127.0.0.1:{free_ports(1)[0]}"
    api = JobsApi(address, timeout=2)
    with pytest.raises(JobsApiUnreachable, match=f"the Ray Jobs API at {address} does not answer"):
        api.status("x-1")
    setup = _setup(tmp_path, ScriptedApi())
    setup.executor.api = api
    started = time.monotonic()
    with pytest.raises(JobError) as caught:
        _predict(setup)
    message = str(caught.value)
    assert message.startswith(f"the job could not be submitted: the Ray Jobs API at {address}")
    assert "\n" not in message and time.monotonic() - started < 30


def test_a_relative_checkpoint_that_exists_here_is_given_as_an_absolute_path(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "w.pt").write_bytes(b"")
    executor = RayJobExecutor(ADDRESS, _models(InferenceSpec(checkpoint="w.pt")), api=ScriptedApi())
    command = executor.entrypoint(
        DatasetSelection(Path("data"), ("08",), KITTI_LAYOUT), Path("jobs/x/predictions")
    )
    argv = shlex.split(command)
    spec = json.loads(argv[argv.index("--inference-spec") + 1])
    assert spec == {"checkpoint": str(tmp_path / "w.pt")}
    assert f"--dataset {tmp_path / 'data'}" in command
    assert f"--out {tmp_path / 'jobs/x/predictions'}" in command


def test_a_jobs_ray_job_gets_its_models_spec(tmp_path):
    """With several models, the entrypoint carries the spec of the job's model (the default's
    without one), and the model's profile reads what is already written."""
    kitti = ModelEntry("kitti", InferenceSpec(checkpoint="/m/kitti.pt"), load_profile(None))
    panda = ModelEntry(
        "panda",
        InferenceSpec(checkpoint="/m/panda.pt", profile="pandaset"),
        load_profile("pandaset"),
    )
    models = ModelCatalog({"kitti": kitti, "panda": panda}, "kitti")
    executor = RayJobExecutor(ADDRESS, models, api=ScriptedApi())

    def spec_of(command: str) -> dict:
        argv = shlex.split(command)
        return json.loads(argv[argv.index("--inference-spec") + 1])

    out = tmp_path / "out"
    assert spec_of(
        executor.entrypoint(DatasetSelection(tmp_path, ("1",), KITTI_LAYOUT), out, "panda")
    ) == {
        "checkpoint": "/m/panda.pt",
        "profile": "pandaset",
    }
    assert spec_of(executor.entrypoint(DatasetSelection(tmp_path, ("08",), KITTI_LAYOUT), out)) == {
        "checkpoint": "/m/kitti.pt"
    }
    # A tables layout's job names its split and version rather than the split's scenes.
    command = executor.entrypoint(
        DatasetSelection(tmp_path, ("scene-0103",), KITTI_LAYOUT, "mini_val", "v1.0-mini"),
        out,
        "panda",
    )
    assert "--split mini_val --version v1.0-mini --out" in command
    assert "--sequences" not in command


def test_a_job_on_a_cluster_survives_more_gateway_restarts_than_one_run_here(tmp_path):
    """`recover` fails a job the gateway stopped MAX_ATTEMPTS times while it ran here, and
    follows a submitted one again (a restart costs it nothing) up to MAX_FOLLOWS."""
    from service.jobs.manager import MAX_ATTEMPTS, MAX_FOLLOWS

    store = JobStore(tmp_path / "jobs.sqlite")
    for name in ("here", "there", "there-long"):
        store.create(name, "dataset", tmp_path, ["08"])
    for _ in range(MAX_ATTEMPTS):
        for name in ("here", "there"):
            store.requeue(name)
            store.start(name)
    store.next_submission("there")
    for _ in range(MAX_FOLLOWS):
        store.requeue("there-long")
        store.start("there-long")
    store.next_submission("there-long")
    manager = JobManager(
        store, object(), tmp_path / "jobs", 3600, models=one_model(load_profile("semantickitti"))
    )
    manager.recover()
    assert store.get("here").state is JobState.failed
    assert store.get("there").state is JobState.queued
    assert store.get("there-long").state is JobState.failed


# Against a real head and a real gateway ---------------------------------------------------------

#: Scans of the dataset most jobs run on (3 labelled in 08, the rest in 11), and of the one a job
#: is stopped in the middle of, which must run long enough to be caught with some scans written.
SCANS, LONG_SCANS = 15, 40


@dataclass
class Cluster:
    """A Ray head with the Jobs API, the data roots the gateway reads, and the reference labels."""

    base: Path
    weights: Path
    roots: Path
    ref: Path
    long_ref: Path
    head: object
    jobs: object  # ray.job_submission.JobSubmissionClient

    def statuses(self, job_id: str) -> dict[str, str]:
        """The Jobs API's submissions of a gateway job, with their statuses."""
        return {
            j.submission_id: str(j.status)
            for j in self.jobs.list_jobs()
            if (j.submission_id or "").startswith(f"{job_id}-")
        }

    def status(self, sid: str) -> str | None:
        return self.statuses(sid.rsplit("-", 1)[0]).get(sid)


def _predict_here(weights: Path, data: Path, out: Path, sequences: list[str]) -> None:
    """`rangeret predict` in this process: the labels every gateway job must equal."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the labels do not depend on it; one thread is quickest here
    try:
        argv = ["predict", "-q", "--dataset", str(data), "--out", str(out), "--sequences"]
        net = ["--checkpoint", str(weights), "--height", "32", "--width", "256", "--device", "cpu"]
        assert rangeret_main([*argv, *sequences, *net]) == 0
    finally:
        torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    pytest.importorskip("ray")
    from ray.job_submission import JobSubmissionClient

    base = tmp_path_factory.mktemp("ray-jobs")
    weights = small_weights(base)
    roots = base / "roots"
    data = build_tree(roots / "data", labelled=3, unlabelled=SCANS - 3)
    long = build_tree(roots / "long", labelled=0, unlabelled=LONG_SCANS)
    broken = build_tree(roots / "broken", labelled=1, unlabelled=1)
    truncated = velodyne_dir(broken, "11", layout=KITTI_LAYOUT) / "000001.bin"
    truncated.write_bytes(truncated.read_bytes()[:-5])
    _predict_here(weights, data, base / "ref", ["08", "11"])
    _predict_here(weights, long, base / "long-ref", ["11"])
    with ray_node(base, num_cpus=2) as head:
        token = head.env["RAY_AUTH_TOKEN"]
        jobs = JobSubmissionClient(head.dashboard, headers={"Authorization": f"Bearer {token}"})
        yield Cluster(base, weights, roots, base / "ref", base / "long-ref", head, jobs)


class Gateways:
    """The gateway process given the head's Jobs API and token, restarted on the same state."""

    def __init__(self, cluster: Cluster) -> None:
        self.state = cluster.base / "state"
        self.weights = cluster.weights
        self.log = cluster.base / "gateway.log"
        self.env = gateway_env(
            self.state,
            [cluster.roots],
            RANGERET_JOBS_ADDRESS=cluster.head.dashboard,
            RANGERET_MAX_RUNNING_JOBS="1",
            RAY_AUTH_MODE="token",
            RAY_AUTH_TOKEN=cluster.head.env["RAY_AUTH_TOKEN"],
        )
        self.current: Gateway = start_gateway(self.weights, self.env, self.log)

    def restart(self, sig: int) -> None:
        self.current.stop(sig)
        self.current = start_gateway(self.weights, self.env, self.log)

    def predictions(self, job_id: str) -> Path:
        return self.state / "jobs" / job_id / "predictions"


@pytest.fixture(scope="module")
def gateways(cluster):
    gateways = Gateways(cluster)
    yield gateways
    gateways.current.stop()


def _until(check, what, gateways: Gateways, timeout: float = 120.0):
    """Poll `check()` until it returns a true value, which is returned; a failure saying `what`
    (a string, or a function giving one then) with the gateway's log when `timeout` seconds pass
    first."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = check()
        if found:
            return found
        time.sleep(0.1)
    said = what() if callable(what) else what
    pytest.fail(
        f"{said} within {timeout:g} s; the gateway's log ends:\n{gateways.current.output()}"
    )


def _settled(cluster: Cluster, gateways: Gateways, job_id: str, expected: dict[str, str]) -> None:
    """Wait until the Jobs API shows exactly the `expected` submissions of a job (its last one
    writes the final record just before its process exits, so it may still be RUNNING)."""
    _until(
        lambda: cluster.statuses(job_id) == expected,
        lambda: f"the Ray jobs of {job_id} are {cluster.statuses(job_id)}, not {expected}",
        gateways,
        timeout=30,
    )


def _start(gateways: Gateways, dataset: str, sequences: list[str]) -> str:
    with gateways.current.client() as client:
        created = client.post("/v1/jobs", json={"dataset": dataset, "sequences": sequences})
    assert created.status_code == 202, created.text
    return created.json()["id"]


def _finished(gateways: Gateways, job_id: str, timeout: float = 180.0) -> dict:
    with gateways.current.client() as client:
        status = wait_job(client, job_id, timeout)
    return status


def _zip_labels(content: bytes, folder: Path) -> dict[str, bytes]:
    with zipfile.ZipFile(io.BytesIO(content)) as zf:
        zf.extractall(folder)
    return tree_bytes(folder)


@pytest.mark.slow
def test_a_dataset_job_is_one_ray_job_with_the_labels_and_report_of_the_cli(
    cluster, gateways, tmp_path
):
    job_id = _start(gateways, "data", ["08", "11"])
    status = _finished(gateways, job_id)
    assert status["state"] == "succeeded", (status, gateways.current.output())
    assert (status["total"], status["done"], status["failed"]) == (SCANS, SCANS, 0)
    with gateways.current.client() as client:
        archive = client.get(f"/v1/jobs/{job_id}/predictions")
        served = client.get(f"/v1/jobs/{job_id}/report").json()
    assert archive.status_code == 200
    labels = _zip_labels(archive.content, tmp_path / "pred")
    assert labels == tree_bytes(cluster.ref) and len(labels) == SCANS

    _settled(cluster, gateways, job_id, {f"{job_id}-1": "SUCCEEDED"})
    info = cluster.jobs.get_job_info(f"{job_id}-1")
    assert info.entrypoint.startswith("python -m workers.predict_job ")
    assert not (info.runtime_env or {}).get("working_dir")  # the nodes' installed package

    argv = ["evaluate", "-q", "--dataset", str(cluster.roots / "data"), "--predictions"]
    argv += [str(tmp_path / "pred"), "--sequences", "08", "--json", str(tmp_path / "eval.json")]
    assert rangeret_main(argv) == 0
    reference = json.loads((tmp_path / "eval.json").read_text())
    for key in ("confusion", "miou", "accuracy", "iou", "per_sequence", "per_distance"):
        assert served[key] == reference[key], key
    assert served["num_scans"] == 3 and served["checkpoint_sha256"]
    assert status["metrics"]["miou"] == reference["miou"]


@pytest.mark.slow
def test_a_panoptic_dataset_job_is_a_ray_job_with_the_panoptic_labels_and_report_of_the_cli(
    cluster, gateways, tmp_path
):
    """`"panoptic": true` reaches the Ray job: its labels are those of `rangeret predict
    --panoptic` and the gateway's report that of `rangeret evaluate --panoptic`."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        argv = ["predict", "-q", "--dataset", str(cluster.roots / "data"), "--sequences", "08"]
        net = ["--checkpoint", str(cluster.weights), "--height", "32", "--width", "256"]
        out = ["--out", str(tmp_path / "ref"), "--device", "cpu", "--panoptic"]
        assert rangeret_main([*argv, *net, *out]) == 0
    finally:
        torch.set_num_threads(threads)
    with gateways.current.client() as client:
        created = client.post(
            "/v1/jobs", json={"dataset": "data", "sequences": ["08"], "panoptic": True}
        )
        assert created.status_code == 202, created.text
        job_id = created.json()["id"]
        status = wait_job(client, job_id, 180)
        archive = client.get(f"/v1/jobs/{job_id}/predictions")
        served = client.get(f"/v1/jobs/{job_id}/report").json()
    assert status["state"] == "succeeded" and status["panoptic"] is True, status
    labels = _zip_labels(archive.content, tmp_path / "pred")
    assert labels == tree_bytes(tmp_path / "ref") and len(labels) == 3
    info = cluster.jobs.get_job_info(f"{job_id}-1")
    argv = shlex.split(info.entrypoint)
    assert json.loads(argv[argv.index("--inference-spec") + 1])["panoptic"] is True
    argv = ["evaluate", "-q", "--dataset", str(cluster.roots / "data"), "--predictions"]
    argv += [str(tmp_path / "ref"), "--sequences", "08", "--panoptic"]
    assert rangeret_main([*argv, "--json", str(tmp_path / "eval.json")]) == 0
    reference = json.loads((tmp_path / "eval.json").read_text())
    assert served["task"] == "panoptic"
    for key in ("pq_mean", "iou_mean", "classes", "per_sequence", "per_distance"):
        assert served[key] == reference[key], key
    assert status["metrics"]["pq"] == pytest.approx(reference["pq_mean"])


@pytest.mark.slow
def test_cancelling_a_job_stops_its_ray_job_and_removes_its_files(cluster, gateways):
    job_id = _start(gateways, "data", ["08", "11"])
    sid, folder = f"{job_id}-1", gateways.state / "jobs" / job_id
    _until(
        lambda: cluster.status(sid) == "RUNNING" and read_progress(folder / "predictions"),
        f"the Ray job {sid} did not start",
        gateways,
    )
    with gateways.current.client() as client:
        cancelled = client.delete(f"/v1/jobs/{job_id}")
        assert cancelled.status_code == 200 and cancelled.json()["state"] == "cancelled"
    _until(
        lambda: cluster.status(sid) == "STOPPED" and not folder.exists(),
        f"the Ray job {sid} was not stopped and the files removed",
        gateways,
        timeout=60,
    )
    time.sleep(1)  # nothing of the stopped job writes into the folder afterwards
    assert not folder.exists() and cluster.statuses(job_id) == {sid: "STOPPED"}
    with gateways.current.client() as client:
        assert client.get(f"/v1/jobs/{job_id}").json()["state"] == "cancelled"


@pytest.mark.slow
def test_a_gateway_killed_or_stopped_mid_job_follows_its_ray_job_again(cluster, gateways, tmp_path):
    job_id = _start(gateways, "long", ["11"])
    sid, out = f"{job_id}-1", gateways.predictions(job_id)
    for sig in (signal.SIGKILL, signal.SIGTERM):
        _until(
            lambda: cluster.status(sid) == "RUNNING" and read_progress(out),
            f"the Ray job {sid} was not running",
            gateways,
        )
        gateways.current.stop(sig)
        assert cluster.status(sid) == "RUNNING", sig  # it runs on
        assert not read_progress(out).finished, f"the job ended before the gateway got {sig!r}"
        gateways.restart(sig)
    status = _finished(gateways, job_id)
    assert status["state"] == "succeeded", (status, gateways.current.output())
    assert (status["total"], status["done"], status["failed"]) == (LONG_SCANS, LONG_SCANS, 0)
    _settled(cluster, gateways, job_id, {sid: "SUCCEEDED"})  # followed again, not resubmitted
    with gateways.current.client() as client:
        archive = client.get(f"/v1/jobs/{job_id}/predictions")
    assert _zip_labels(archive.content, tmp_path / "pred") == tree_bytes(cluster.long_ref)


@pytest.mark.slow
def test_a_ray_job_stopped_behind_the_gateways_back_is_submitted_again(cluster, gateways):
    job_id = _start(gateways, "long", ["11"])
    first, second = f"{job_id}-1", f"{job_id}-2"
    out = gateways.predictions(job_id)

    def some_written():
        record = read_progress(out)
        return record is not None and 3 <= record.done <= LONG_SCANS - 10

    _until(some_written, f"the Ray job {first} wrote no scan", gateways)
    cluster.jobs.stop_job(first)
    _until(lambda: cluster.status(first) == "STOPPED", f"{first} did not stop", gateways, 60)
    written = {p.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in out.rglob("*.label")}
    assert 3 <= len(written) < LONG_SCANS

    status = _finished(gateways, job_id)
    assert status["state"] == "succeeded", (status, gateways.current.output())
    assert (status["total"], status["done"], status["failed"]) == (LONG_SCANS, LONG_SCANS, 0)
    _settled(cluster, gateways, job_id, {first: "STOPPED", second: "SUCCEEDED"})
    assert tree_bytes(out) == tree_bytes(cluster.long_ref)
    again = {p.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in out.rglob("*.label")}
    assert {name: again[name] for name in written} == written  # none written twice
    final = read_progress(out)
    assert final.finished and final.done == final.total == LONG_SCANS


@pytest.mark.slow
def test_an_unreadable_scan_fails_the_job_naming_it(cluster, gateways):
    job_id = _start(gateways, "broken", ["08", "11"])
    status = _finished(gateways, job_id)
    assert status["state"] == "failed", (status, gateways.current.output())
    assert "1 of 2 scans could not be predicted" in status["reason"]
    assert status["failed"] == 1 and len(status["errors"]) == 1
    assert status["errors"][0].startswith("11/000001: ")
    record = read_progress(gateways.predictions(job_id))
    assert record.finished and record.error is None
    assert list(record.failures) == ["11/000001"] and (record.total, record.done) == (2, 1)
    _settled(cluster, gateways, job_id, {f"{job_id}-1": "FAILED"})  # exit 1, not submitted again


@pytest.mark.slow
def test_a_refused_ray_token_is_one_sentence_naming_the_address(cluster, tmp_path):
    script = (
        "import sys\n"
        "from service.jobs.jobs_api import JobsApi, JobsApiError\n"
        "try:\n"
        "    JobsApi(sys.argv[1]).status('x-1')\n"
        "except JobsApiError as exc:\n"
        "    print(type(exc).__name__, exc)\n"
    )
    env = dict(os.environ, RAY_AUTH_MODE="token", RAY_AUTH_TOKEN="0" * 64)
    run = subprocess.run(
        [sys.executable, "-c", script, cluster.head.dashboard],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    line = run.stdout.strip()
    assert line.startswith("JobsApiError the Ray Jobs API at "), run.stdout + run.stderr
    assert cluster.head.dashboard in line and "refused the gateway's Ray token" in line
    assert "\n" not in line


def test_a_panoptic_jobs_ray_job_finds_objects_and_a_plain_one_does_not(tmp_path):
    """A panoptic job's Ray job gets its model's spec with `panoptic` (and the model's clustering
    options); a plain job's spec has no `panoptic`, whatever the model's own."""

    def run(api, sid, n):
        _finish(setup.out)
        api.statuses[sid] = "SUCCEEDED"

    api = ScriptedApi(run)
    setup = _setup(tmp_path, api)
    clustering = {"panoptic": True, "cluster_angle": 20.0, "min_cluster_points": 4}
    spec = InferenceSpec(checkpoint="weights.pt", height=32, width=256, **clustering)
    setup.executor = RayJobExecutor(ADDRESS, _models(spec), api=api, poll_s=0.01)
    args = (setup.entries, setup.data, ["08", "11"], setup.out, lambda *c: None, setup.control)
    assert setup.executor.predict(*args, panoptic=True) == {}

    def spec_of(command: str) -> dict:
        argv = shlex.split(command)
        return json.loads(argv[argv.index("--inference-spec") + 1])

    found = spec_of(api.submitted[0][1])
    assert {k: found.get(k) for k in clustering} == clustering
    plain = setup.executor.entrypoint(
        DatasetSelection(setup.data, ("08",), KITTI_LAYOUT), setup.out
    )
    assert "panoptic" not in spec_of(plain) and spec_of(plain)["cluster_angle"] == 20.0
