"""The gateway's bounds and edges against a real uvicorn process on 127.0.0.1.

Deeply nested JSON is a 400; a client that disconnects mid-body is counted as such, not as a
server error; a 405 names every method of its path; links that lead out of the data roots are
refused without naming where they lead; single scans are admitted within a bound of requests and
bytes (503 with Retry-After beyond); jobs run side by side, the queue and the jobs' disk are
capped (429, 507); `/healthz` says little without the token.
"""

from __future__ import annotations

import os
import re
import socket
import time
from collections.abc import Iterator

import httpx
import pytest

from rangeret.dataset.layout import KITTI_LAYOUT, velodyne_dir
from rangeret.io.scans import KITTI_RECORD, read_scan, write_scan
from service.schemas import ErrorResponse
from tests.support.gateway import (
    AUTH,
    OCTET,
    Gateway,
    assert_error,
    gateway_env,
    start_gateway,
    wait_job,
)
from tests.support.paths import data_path
from tests.support.workers import small_weights

#: Scans of the long sequence (hard links of the real scan, so they cost no disk).
LONG_SCANS = 300
#: Bytes a job over the long sequence is expected to write: a prediction and its zip copy.
LONG_JOB_BYTES = 2 * 4 * 123_389 * LONG_SCANS


@pytest.fixture(scope="module")
def setup(tmp_path_factory) -> dict:
    """Weights; a data root with a long sequence (09), a one-scan sequence (08), links that lead
    out of the root and a link that stays inside it; a folder outside the roots."""
    base = tmp_path_factory.mktemp("hardening")
    weights = small_weights(base)
    roots = base / "roots"
    points = read_scan(data_path("semantickitti-scan", "000000.bin"))
    data = roots / "data"
    write_scan(
        velodyne_dir(data, "08", layout=KITTI_LAYOUT) / "000000.bin",
        points[::50],
        record=KITTI_RECORD,
    )
    first = velodyne_dir(data, "09", layout=KITTI_LAYOUT) / "000000.bin"
    write_scan(first, points, record=KITTI_RECORD)
    for i in range(1, LONG_SCANS):
        os.link(first, first.with_name(f"{i:06d}.bin"))
    outside = base / "outside"
    write_scan(
        velodyne_dir(outside, "08", layout=KITTI_LAYOUT) / "000000.bin",
        points[::60],
        record=KITTI_RECORD,
    )
    (roots / "linked-sequence" / "sequences").mkdir(parents=True)
    (roots / "linked-sequence" / "sequences" / "08").symlink_to(outside / "sequences" / "08")
    velodyne_dir(roots / "linked-scan", "08", layout=KITTI_LAYOUT).mkdir(parents=True)
    (velodyne_dir(roots / "linked-scan", "08", layout=KITTI_LAYOUT) / "000000.bin").symlink_to(
        velodyne_dir(outside, "08", layout=KITTI_LAYOUT) / "000000.bin"
    )
    (roots / "inner-link").symlink_to(data)
    return {"base": base, "weights": weights, "roots": roots, "outside": outside, "points": points}


@pytest.fixture(scope="module")
def gateway(setup) -> Iterator[Gateway]:
    env = gateway_env(
        setup["base"] / "state",
        [setup["roots"]],
        RANGERET_MAX_QUEUED_SCANS="2",
        RANGERET_MAX_QUEUED_BYTES=str(3_000_000),
        RANGERET_MAX_RUNNING_JOBS="2",
        RANGERET_MAX_QUEUED_JOBS="1",
        RANGERET_MAX_JOB_BYTES=str(int(2.5 * LONG_JOB_BYTES)),
    )
    gw = start_gateway(setup["weights"], env, setup["base"] / "gateway.log")
    yield gw
    gw.stop()


def _held_scan_request(gw: Gateway, declared: int) -> socket.socket:
    """A POST /v1/scans that declares `declared` bytes and sends a few: the gateway holds it
    while it waits for the rest."""
    host, port = gw.url.removeprefix("http://").split(":")
    sock = socket.create_connection((host, int(port)), timeout=30)
    head = (
        f"POST /v1/scans HTTP/1.1\r\nHost: {host}\r\nAuthorization: {AUTH['Authorization']}\r\n"
        f"Content-Type: application/octet-stream\r\nContent-Length: {declared}\r\n\r\n"
    )
    sock.sendall(head.encode() + b"\0" * 16)
    return sock


def _metric(gw: Gateway, pattern: str) -> float:
    text = httpx.get(gw.url + "/metrics", timeout=10).text
    found = re.search("(?m)^" + pattern, text)
    return float(found.group(1)) if found else 0.0


def _wait_for(condition, timeout: float = 30, what: str = "the condition") -> None:
    deadline = time.time() + timeout
    while not condition():
        if time.time() > deadline:
            pytest.fail(f"{what} did not happen in {timeout} s")
        time.sleep(0.1)


def test_deeply_nested_json_is_a_400(gateway):
    with gateway.client() as client:
        body = '{"dataset": ' + "[" * 100_000 + "]" * 100_000 + "}"
        r = client.post("/v1/jobs", content=body, headers={"Content-Type": "application/json"})
        assert "nested too deeply" in assert_error(r, 400)


def test_a_client_that_disconnects_mid_body_is_no_server_error(gateway):
    route = r'rangeret_http_requests_total\{method="POST",route="/v1/scans",status="%s"\} (\S+)'
    before = _metric(gateway, route % "client_disconnect")
    sock = _held_scan_request(gateway, 16_000)
    time.sleep(0.3)
    sock.close()
    _wait_for(
        lambda: _metric(gateway, route % "client_disconnect") == before + 1,
        what="the disconnect being counted",
    )
    assert _metric(gateway, route % "500") == 0
    log = gateway.output()
    assert "Traceback" not in log
    assert log.count("the client disconnected before its request was read") == 1


def test_405_lists_every_method_of_the_path(gateway):
    with gateway.client() as client:
        r = client.put("/v1/jobs")
        assert_error(r, 405)
        assert set(r.headers["allow"].split(", ")) >= {"GET", "POST"}
        r = client.put("/v1/jobs/0123")
        assert_error(r, 405)
        assert set(r.headers["allow"].split(", ")) >= {"GET", "DELETE"}
        assert "POST" not in r.headers["allow"]


def test_links_out_of_the_data_roots_are_refused_without_naming_their_target(setup, gateway):
    outside = str(setup["outside"])
    with gateway.client() as client:
        for dataset in ("linked-sequence", "linked-scan"):
            r = client.post("/v1/jobs", json={"dataset": dataset, "sequences": ["08"]})
            detail = assert_error(r, 403)
            assert "outside the data roots" in detail and "08/000000" in detail
            assert outside not in detail and str(setup["base"]) not in detail
        inner = client.post("/v1/jobs", json={"dataset": "inner-link", "sequences": ["08"]})
        assert inner.status_code == 202, inner.text
        assert wait_job(client, inner.json()["id"])["state"] == "succeeded"
        # The dataset root itself linked out of the roots.
        (setup["roots"] / "root-link").symlink_to(setup["outside"])
        r = client.post("/v1/jobs", json={"dataset": "root-link", "sequences": ["08"]})
        assert outside not in assert_error(r, 403)


def test_single_scans_are_admitted_within_the_bounds(setup, gateway):
    small = setup["points"][::100].tobytes()
    refused = r"rangeret_scans_refused_total (\S+)"
    before = _metric(gateway, refused)
    with gateway.client() as client:
        held = [_held_scan_request(gateway, 160_000) for _ in range(2)]
        try:
            time.sleep(0.5)
            r = client.post("/v1/scans", content=small, headers=OCTET)
            assert "RANGERET_MAX_QUEUED_SCANS" in assert_error(r, 503)
            assert r.headers["retry-after"] == "1"
        finally:
            for sock in held:
                sock.close()
        _wait_for(
            lambda: client.post("/v1/scans", content=small, headers=OCTET).status_code == 200,
            what="a scan being labelled once the held requests were gone",
        )
        big = _held_scan_request(gateway, 2_000_000)
        try:
            time.sleep(0.5)
            r = client.post("/v1/scans", content=b"\0" * 1_600_000, headers=OCTET)
            assert "RANGERET_MAX_QUEUED_BYTES" in assert_error(r, 503)
            ok = client.post("/v1/scans", content=small, headers=OCTET)
            assert ok.status_code == 200 and len(ok.content) == 4 * (len(small) // 16)
        finally:
            big.close()
    assert _metric(gateway, refused) >= before + 2  # and any retry while the held ones left


def test_jobs_run_side_by_side_and_the_queue_and_disk_are_capped(gateway):
    def state(client: httpx.Client, job_id: str) -> str:
        return client.get(f"/v1/jobs/{job_id}").json()["state"]

    with gateway.client() as client:
        long_job = {"dataset": "data", "sequences": ["09"]}
        short_job = {"dataset": "data", "sequences": ["08"]}
        first = client.post("/v1/jobs", json=long_job).json()["id"]
        short = client.post("/v1/jobs", json=short_job).json()["id"]
        assert wait_job(client, short)["state"] == "succeeded"
        assert state(client, first) == "running", "a short job finished beside a long one"

        second = client.post("/v1/jobs", json=long_job).json()["id"]
        _wait_for(lambda: state(client, second) == "running", what="a second long job running")
        waiting = client.post("/v1/jobs", json=short_job).json()["id"]
        assert state(client, waiting) == "queued"
        detail = assert_error(client.post("/v1/jobs", json=short_job), 429)
        assert "RANGERET_MAX_QUEUED_JOBS" in detail
        client.delete(f"/v1/jobs/{waiting}")

        detail = assert_error(client.post("/v1/jobs", json=long_job), 507)
        assert "RANGERET_MAX_JOB_BYTES" in detail
        assert state(client, first) == state(client, second) == "running"
        for job_id in (first, second):
            assert client.delete(f"/v1/jobs/{job_id}").json()["state"] == "cancelled"


def test_healthz_says_little_without_the_token(setup, gateway):
    anonymous = httpx.get(gateway.url + "/healthz", timeout=10)
    wrong = httpx.get(
        gateway.url + "/healthz", headers={"Authorization": "Bearer wrong"}, timeout=10
    )
    for r in (anonymous, wrong):
        assert r.status_code == 200
        assert r.json().keys() == {"status", "model", "profile", "models", "version"}
        assert r.json()["status"] == "ok" and r.json()["profile"] == "semantickitti"
        assert r.json()["models"] == {"default": "semantickitti"}
        assert str(setup["weights"]) not in r.text and "pid" not in r.text
    with gateway.client() as client:
        full = client.get("/healthz").json()
    assert full["workers"] and full["workers"][0]["pid"] > 0
    assert full["model"] == anonymous.json()["model"] == full["workers"][0]["model"]


def test_error_sentences(gateway):
    with gateway.client() as client:
        r = client.post("/v1/scans", content=b"\0" * 17, headers=OCTET)
        example = ErrorResponse.model_json_schema()["properties"]["detail"]["examples"][0]
        assert assert_error(r, 400) == example
        r = client.post("/v1/scans", content=b"\0" * 16)
        assert assert_error(r, 415).endswith("this request has no Content-Type.")
        r = client.post("/v1/scans", content=b"\0" * 16, headers={"Content-Type": "text/plain"})
        assert "text/plain" in assert_error(r, 415)
