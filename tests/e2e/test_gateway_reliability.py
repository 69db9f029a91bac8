"""Against real `rangeret serve` processes: start-up removes only the job folders the gateway
made, trailing-slash requests are never redirected to another host, a zip member whose name
holds a NUL byte is refused, clean stops do not count towards the restarts a job survives, and a
job store or state folder that cannot be used is one line before any weights load."""

from __future__ import annotations

import io
import os
import signal
import socket
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import httpx
import numpy as np
import pytest

from rangeret.dataset.layout import KITTI_LAYOUT, velodyne_dir
from rangeret.io.scans import KITTI_RECORD, read_scan, write_scan
from tests.support.gateway import assert_error, gateway_env, start_gateway, wait_job
from tests.support.paths import data_path
from tests.support.workers import small_weights

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
        write_scan(
            velodyne_dir(root, "42", layout=KITTI_LAYOUT) / f"{i:06d}.bin",
            points[i % 3 :: 3],
            record=KITTI_RECORD,
        )
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


def _damaged_page(path: Path) -> None:
    """A real job database with one of its pages overwritten by garbage."""
    from service.jobs import JobStore

    store = JobStore(path)
    for i in range(300):
        store.create(f"{i:032x}", "dataset", path.parent, ["08"] * 20)
    store.close()
    data = bytearray(path.read_bytes())
    page = 4096
    data[2 * page : 3 * page] = os.urandom(page)
    path.write_bytes(bytes(data))


@pytest.mark.parametrize(
    "damage",
    ["random-bytes", "truncated", "damaged-page", "folder-in-its-place", "state-dir-is-a-file"],
)
def test_a_job_store_or_state_folder_that_cannot_be_used_is_one_line(tmp_path, damage):
    """Each is refused before the weights load, naming the file and the problem."""
    state = tmp_path / "state"
    database = state / "jobs.sqlite"
    state.mkdir()
    if damage == "random-bytes":
        database.write_bytes(os.urandom(8192))
        named = database
    elif damage == "truncated":
        _damaged_page(database)
        database.write_bytes(database.read_bytes()[:5000])
        named = database
    elif damage == "damaged-page":
        _damaged_page(database)
        named = database
    elif damage == "folder-in-its-place":
        database.mkdir()
        named = database
    else:
        state.rmdir()
        state.write_text("not a folder")
        named = state
    env = gateway_env(state, [tmp_path])
    run = subprocess.run(
        [sys.executable, "-m", "service", "--checkpoint", str(tmp_path / "absent.pt")],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert run.returncode == 1, run.stderr[-2000:]
    assert "Traceback" not in run.stderr and run.stderr.count("\n") == 1, run.stderr[-2000:]
    assert str(named) in run.stderr and "absent.pt" not in run.stderr, run.stderr


def _hosted(gw, path: str, host: str, method: str = "GET", **headers: str) -> httpx.Response:
    with gw.client() as client:
        return client.request(method, path, headers={"Host": host, **headers}, json={})


def test_a_gateway_without_a_token_answers_only_its_own_names_and_origin(tmp_path):
    """DNS rebinding and other origins' pages: the Host allow-list, /healthz for probes, and
    state-changing requests refused when the browser says (or the Origin shows) another origin
    sent them; scripts without those headers go on as before."""
    env = gateway_env(tmp_path / "state", [tmp_path], token=None)
    gw = start_gateway(small_weights(tmp_path), env, tmp_path / "gateway.log")
    port = gw.url.rsplit(":", 1)[1]
    try:
        assert "RANGERET_ALLOWED_HOSTS" in assert_error(
            _hosted(gw, "/v1/jobs", "attacker.example"), 400
        )
        assert _hosted(gw, "/healthz", "10.1.2.3:8000").status_code == 200
        for host in (f"localhost:{port}", f"127.0.0.1:{port}", f"[::1]:{port}"):
            assert _hosted(gw, "/v1/jobs", host).status_code == 200, host
        own = f"127.0.0.1:{port}"
        for headers in (
            {"Origin": "http://evil.example"},
            {"Origin": "null"},
            {"Sec-Fetch-Site": "cross-site", "Origin": f"http://{own}"},
            {"Sec-Fetch-Site": "same-site"},
        ):
            answer = _hosted(gw, "/v1/jobs", own, "POST", **headers)
            assert "another origin" in assert_error(answer, 403), headers
        for headers in ({}, {"Origin": f"http://{own}"}, {"Sec-Fetch-Site": "same-origin"}):
            answer = _hosted(gw, "/v1/jobs", own, "POST", **headers)  # on to the app: no dataset
            assert answer.status_code == 400 and "another origin" not in answer.text, headers
        with gw.client() as client:
            assert client.get("/v1/jobs").json()["jobs"] == []

        # RFC 9112: one Host line, and an absolute-form target's authority is the host judged.
        twice = _raw(gw, f"GET /v1/jobs HTTP/1.1\r\nHost: {own}\r\nHost: {own}\r\n")
        assert twice.startswith(b"HTTP/1.1 400 ") and b"2 Host lines" in twice, twice
        elsewhere = _raw(gw, f"GET http://attacker.example/v1/jobs HTTP/1.1\r\nHost: {own}\r\n")
        assert elsewhere.startswith(b"HTTP/1.1 400 ") and b"attacker.example" in elsewhere
        ours = _raw(gw, f"GET http://{own}/v1/jobs HTTP/1.1\r\nHost: attacker.example\r\n")
        assert ours.startswith(b"HTTP/1.1 200 ") and b'"jobs":[]' in ours, ours
    finally:
        gw.stop()


def _raw(gw, head: str) -> bytes:
    """The whole answer to a request head sent as written, on a connection of its own."""
    port = int(gw.url.rsplit(":", 1)[1])
    with socket.create_connection(("127.0.0.1", port), timeout=30) as sock:
        sock.sendall(head.encode() + b"Connection: close\r\n\r\n")
        answer = b""
        while chunk := sock.recv(65536):
            answer += chunk
    return answer


def test_a_gateway_with_a_token_takes_any_host_unless_given_a_list(gateway, tmp_path):
    assert _hosted(gateway, "/v1/jobs", "rangeret-gateway").status_code == 200
    env = gateway_env(tmp_path / "state", [tmp_path], RANGERET_ALLOWED_HOSTS="rangeret.example")
    listed = start_gateway(small_weights(tmp_path), env, tmp_path / "gateway.log")
    try:
        assert _hosted(listed, "/v1/jobs", "rangeret.example").status_code == 200
        assert_error(_hosted(listed, "/v1/jobs", "rangeret-gateway"), 400)
        assert _hosted(listed, "/healthz", "10.1.2.3").status_code == 200
    finally:
        listed.stop()


def test_a_job_whose_folder_is_removed_fails_naming_no_server_path(tmp_path):
    """The job's predictions are deleted while it runs: it fails saying so, its `done` counts the
    files that are really there, and neither its reason nor its errors quote the state folder."""
    import shutil

    points = read_scan(data_path("semantickitti-scan", "000000.bin"))
    for i in range(40):
        write_scan(
            velodyne_dir(tmp_path / "long", "42", layout=KITTI_LAYOUT) / f"{i:06d}.bin",
            points[i % 3 :: 3],
            record=KITTI_RECORD,
        )
    state = tmp_path / "state"
    env = gateway_env(state, [tmp_path], RANGERET_BATCH_SIZE="1")
    gw = start_gateway(small_weights(tmp_path), env, tmp_path / "gateway.log")
    try:
        with gw.client() as client:
            job_id = client.post("/v1/jobs", json={"dataset": "long", "sequences": ["42"]}).json()[
                "id"
            ]
            out = state / "jobs" / job_id / "predictions"
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline and len(list(out.rglob("*.label"))) < 3:
                time.sleep(0.05)
            shutil.rmtree(out)
            status = wait_job(client, job_id, timeout=300)
    finally:
        gw.stop()
    assert status["state"] == "failed", status
    text = " ".join([status["reason"], *status["errors"]])
    assert str(tmp_path) not in text and "Errno" not in text, text
    assert status["done"] == len(list(out.rglob("*.label"))) < 40, status


def test_a_scan_swapped_for_a_link_out_of_the_roots_while_its_job_runs_is_refused(tmp_path):
    """The roots are checked when a job starts and again when each scan is read: a scan replaced
    by a link to a file outside them after the job started is that scan's failure, and nothing
    of the outside file is labelled."""
    points = read_scan(data_path("semantickitti-scan", "000000.bin"))
    roots = tmp_path / "roots"
    for i in range(40):
        write_scan(
            velodyne_dir(roots / "long", "42", layout=KITTI_LAYOUT) / f"{i:06d}.bin",
            points[i % 3 :: 3],
            record=KITTI_RECORD,
        )
    outside = tmp_path / "outside.bin"
    write_scan(outside, points[::5], record=KITTI_RECORD)
    state = tmp_path / "state"
    env = gateway_env(state, [roots], RANGERET_BATCH_SIZE="1")
    gw = start_gateway(small_weights(tmp_path), env, tmp_path / "gateway.log")
    last = velodyne_dir(roots / "long", "42", layout=KITTI_LAYOUT) / "000039.bin"
    try:
        with gw.client() as client:
            job_id = client.post("/v1/jobs", json={"dataset": "long", "sequences": ["42"]}).json()[
                "id"
            ]
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline:
                status = client.get(f"/v1/jobs/{job_id}").json()
                if status["state"] == "running" and status["done"] >= 1:
                    break
                time.sleep(0.02)
            assert status["done"] < 39, status
            last.unlink()
            last.symlink_to(outside)
            status = wait_job(client, job_id, timeout=300)
    finally:
        gw.stop()
    assert status["state"] == "failed" and status["failed"] == 1, status
    reason = "long/sequences/42/velodyne/000039.bin: it leads outside the folders this run may read"
    assert status["errors"] == [f"42/000039: {reason}"], status["errors"]
    out = state / "jobs" / job_id / "predictions" / "sequences" / "42" / "predictions"
    assert not (out / "000039.label").exists() and len(list(out.glob("*.label"))) == 39


@pytest.fixture
def small_disk(tmp_path):
    """A 1 MiB tmpfs of the test's own (mounting one needs root), and a way to fill it."""
    if os.geteuid() != 0:
        pytest.skip("a full disk is made with a tmpfs, which only root may mount")
    disk = tmp_path / "disk"
    disk.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(disk)], check=True)

    def fill() -> Path:
        filler = disk / "filler"
        f = open(filler, "ab", buffering=0)  # noqa: SIM115
        try:
            while True:
                f.write(b"\0" * 4096)
        except OSError:
            pass
        finally:
            f.close()
        return filler

    try:
        yield disk, fill
    finally:
        subprocess.run(["umount", "-l", str(disk)], check=False)


def _long_dataset(root: Path, scans: int = 60, stride: int = 3) -> None:
    points = read_scan(data_path("semantickitti-scan", "000000.bin"))
    for i in range(scans):
        write_scan(
            velodyne_dir(root, "42", layout=KITTI_LAYOUT) / f"{i:06d}.bin",
            points[i % stride :: stride],
            record=KITTI_RECORD,
        )


def test_a_full_disk_under_the_job_database_is_507_and_fails_the_running_job(tmp_path, small_disk):
    disk, fill = small_disk
    _long_dataset(tmp_path / "long", scans=100)
    database = disk / "jobs.sqlite"
    env = gateway_env(
        tmp_path / "state", [tmp_path], RANGERET_DATABASE=str(database), RANGERET_BATCH_SIZE="1"
    )
    gw = start_gateway(small_weights(tmp_path), env, tmp_path / "gateway.log")
    try:
        with gw.client() as client:
            job = {"dataset": "long", "sequences": ["42"]}
            job_id = client.post("/v1/jobs", json=job).json()["id"]
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline:
                status = client.get(f"/v1/jobs/{job_id}").json()
                if status["state"] == "running" and status["done"] >= 1:
                    break
                time.sleep(0.05)
            filler = fill()
            detail = assert_error(client.post("/v1/jobs", json=job), 507)
            assert str(database) in detail and "full disk" in detail, detail
            time.sleep(1)  # the running job's next progress record meets the full disk
            assert client.get(f"/v1/jobs/{job_id}").json()["done"] < 100
            filler.unlink()  # the space comes back
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                status = client.get(f"/v1/jobs/{job_id}").json()
                if status["state"] != "running":
                    break
                time.sleep(0.2)
    finally:
        gw.stop()
    assert status["state"] == "failed" and str(database) in status["reason"], status
    assert "Traceback" not in gw.output()


def test_an_upload_or_a_job_that_does_not_fit_the_jobs_disk_is_507(tmp_path, small_disk):
    disk, _ = small_disk
    _long_dataset(tmp_path / "long", scans=20)
    env = gateway_env(tmp_path / "state", [tmp_path], RANGERET_JOBS_DIR=str(disk / "jobs"))
    gw = start_gateway(small_weights(tmp_path), env, tmp_path / "gateway.log")
    try:
        with gw.client() as client:
            answer = client.post("/v1/jobs", json={"dataset": "long", "sequences": ["42"]})
            detail = assert_error(answer, 507)
            assert "bytes free" in detail and str(disk / "jobs") in detail, detail
            points = read_scan(data_path("semantickitti-scan", "000000.bin"))
            buf = io.BytesIO()
            with zipfile.ZipFile(buf, "w") as zf:  # about 2.6 MB, stored
                for i in range(8):
                    name = f"sequences/11/velodyne/{i:06d}.bin"
                    zf.writestr(name, points[i % 6 :: 6].tobytes())
            answer = client.post(
                "/v1/jobs", files={"archive": ("big.zip", buf.getvalue(), "application/zip")}
            )
            detail = assert_error(answer, 507)
            assert str(disk) in detail, detail
            assert client.get("/v1/jobs").json()["jobs"] == []
    finally:
        gw.stop()
