"""Against real `rangeret serve` processes: start-up removes only the job folders the gateway
made, trailing-slash requests are never redirected to another host, a zip member whose name
holds a NUL byte is refused, and clean stops do not count towards the restarts a job survives."""

from __future__ import annotations

import io
import signal
import time
import zipfile

import numpy as np
import pytest
from conftest import data_path
from gateway_helpers import assert_error, gateway_env, start_gateway, wait_job
from workers_helpers import small_weights

from rangeret.io import read_scan, write_scan
from rangeret.layout import velodyne_dir

pytestmark = pytest.mark.slow


def test_start_up_removes_only_the_folders_the_gateway_made(tmp_path):
    jobs = tmp_path / "jobs"
    for name in ("photos", "important-project/src", "0123456789abcdef0123456789abcdef"):
        (jobs / name).mkdir(parents=True)
        (jobs / name / "keep.txt").write_text("mine")
    (jobs / "notes.txt").write_text("mine too")
    cut_short = jobs / ("f" * 32)  # an upload the gateway began and never recorded
    cut_short.mkdir()
    (cut_short / ".rangeret-job").write_text("f" * 32 + "\n")
    (cut_short / "upload.part").write_bytes(b"\0" * 100)
    env = gateway_env(tmp_path / "state", [tmp_path], RANGERET_JOBS_DIR=str(jobs))
    gw = start_gateway(small_weights(tmp_path), env, tmp_path / "gateway.log")
    gw.stop()
    assert not cut_short.exists()
    for name in ("photos", "important-project/src", "0123456789abcdef0123456789abcdef"):
        assert (jobs / name / "keep.txt").read_text() == "mine", name
    assert (jobs / "notes.txt").read_text() == "mine too"
    log = gw.output()
    assert "did not make" in log and "photos" in log and "important-project" in log
    removed = [line for line in log.splitlines() if "removing" in line]
    assert len(removed) == 1 and str(cut_short) in removed[0], removed


@pytest.fixture(scope="module")
def gateway(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("reliability")
    gw = start_gateway(small_weights(tmp), gateway_env(tmp / "state", [tmp]), tmp / "gateway.log")
    yield gw
    gw.stop()


def test_a_trailing_slash_is_never_redirected_to_the_requests_host(gateway):
    with gateway.client() as client:
        answer = client.get("/v1/jobs/", headers={"Host": "evil.example"})
        assert "location" not in answer.headers
        assert_error(answer, 404)
        assert client.get("/v1/jobs").status_code == 200


def test_a_zip_member_name_with_a_nul_byte_is_refused(gateway):
    scan = np.zeros((10, 4), np.float32).tobytes()
    evil = "sequences/02/velodyne/000000.bin\0../../../../etc/passwd"
    placeholder = evil.replace("\0", "x")  # the same length, so only the NUL differs after
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr(placeholder, scan)
    data = buf.getvalue().replace(placeholder.encode(), evil.encode())
    assert data.count(evil.encode()) == 2  # the local header and the central directory
    with gateway.client() as client:
        answer = client.post(
            "/v1/jobs", files={"archive": ("evil.zip", data, "application/octet-stream")}
        )
        detail = assert_error(answer, 400)
    assert "NUL byte" in detail and "sequences/02/velodyne/" in detail


def test_clean_stops_do_not_count_towards_the_restarts_a_job_survives(tmp_path):
    """Two SIGTERMs and a SIGKILL while a job runs: before, the job failed at the next start as
    stopped three times; now only the kill counts, and the job resumes and finishes."""
    points = read_scan(data_path("semantickitti-scan", "000000.bin"))
    root = tmp_path / "long"
    for i in range(60):
        write_scan(velodyne_dir(root, "42") / f"{i:06d}.bin", points[i % 3 :: 3])
    weights = small_weights(tmp_path)
    env = gateway_env(tmp_path / "state", [tmp_path], RANGERET_BATCH_SIZE="1")
    job_id = None
    done = 0
    for i, sig in enumerate((signal.SIGTERM, signal.SIGTERM, signal.SIGKILL)):
        gw = start_gateway(weights, env, tmp_path / f"run-{i}.log")
        try:
            with gw.client() as client:
                if job_id is None:
                    answer = client.post("/v1/jobs", json={"dataset": "long", "sequences": ["42"]})
                    job_id = answer.json()["id"]
                deadline = time.monotonic() + 120
                while time.monotonic() < deadline:
                    status = client.get(f"/v1/jobs/{job_id}").json()
                    if status["state"] == "running" and status["done"] > done:
                        break
                    time.sleep(0.05)
                assert status["state"] == "running" and status["done"] < 60, status
                done = status["done"]
        finally:
            gw.stop(sig)
    gw = start_gateway(weights, env, tmp_path / "last.log")
    try:
        with gw.client() as client:
            final = wait_job(client, job_id, timeout=300)
    finally:
        gw.stop()
    assert final["state"] == "succeeded", final
    assert (final["total"], final["done"], final["failed"]) == (60, 60, 0)
