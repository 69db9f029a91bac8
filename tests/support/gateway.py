"""A real gateway process for the HTTP tests: `rangeret serve` (uvicorn) on a free loopback port,
its environment, and the checks every error answer must pass."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest

from tests.support.paths import REPO

TOKEN = "test-token-1234"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
OCTET = {"Content-Type": "application/octet-stream"}
NET = ["--height", "32", "--width", "256", "--device", "cpu"]
LIMITS = {
    "RANGERET_MAX_BODY_BYTES": str(4 << 20),
    "RANGERET_MAX_POINTS": "200000",
    "RANGERET_MAX_ARCHIVE_BYTES": str(8 << 20),
    "RANGERET_MAX_ARCHIVE_MEMBERS": "50",
    "RANGERET_BATCH_SIZE": "2",
    "RANGERET_BATCH_WAIT_MS": "20",
}


# A gateway process ---------------------------------------------------------------------------


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class Gateway:
    url: str
    proc: subprocess.Popen
    log: Path

    def client(self, auth: bool = True, timeout: float = 60) -> httpx.Client:
        return httpx.Client(base_url=self.url, headers=AUTH if auth else {}, timeout=timeout)

    def output(self) -> str:
        return self.log.read_text(errors="replace")[-4000:]

    def stop(self, sig: int = signal.SIGTERM) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)


def gateway_env(
    state: Path, roots: list[Path], token: str | None = TOKEN, **extra: str
) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("RANGERET_")}
    env.update(LIMITS)
    env.update(
        RANGERET_STATE_DIR=str(state), RANGERET_DATA_ROOTS=os.pathsep.join(map(str, roots)), **extra
    )
    if token:
        env["RANGERET_API_TOKEN"] = token
    return env


def start_gateway(
    weights: Path | None, env: dict[str, str], log: Path, *args: str, net: Sequence[str] = NET
) -> Gateway:
    """`rangeret serve` of `weights` (None: the models file among `args` names them) with the
    network options `net` (default: the small weights' 32 x 256 on the CPU) and `args`, once it
    answers /healthz."""
    port = free_port()
    cmd = [
        sys.executable,
        "-m",
        "service",
        *(["--checkpoint", str(weights)] if weights is not None else []),
        *net,
        "--port",
        str(port),
        "--log-level",
        "warning",
        *args,
    ]
    with open(log, "ab") as out:
        proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT)
    return wait_healthy(Gateway(f"http://127.0.0.1:{port}", proc, log))


def wait_healthy(gw: Gateway, timeout: float = 120) -> Gateway:
    """`gw` once it answers /healthz with 200; the test fails with its log's end when its process
    exits first or it does not answer within `timeout` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if gw.proc.poll() is not None:
            pytest.fail(f"the gateway exited with {gw.proc.returncode}:\n{gw.output()}")
        try:
            if httpx.get(gw.url + "/healthz", timeout=2).status_code == 200:
                return gw
        except httpx.TransportError:
            pass
        time.sleep(0.2)
    gw.stop(signal.SIGKILL)
    pytest.fail(f"the gateway did not answer in time:\n{gw.output()}")


def wait_job(client: httpx.Client, job_id: str, timeout: float = 120) -> dict:
    deadline = time.time() + timeout
    while time.time() < deadline:
        status = client.get(f"/v1/jobs/{job_id}").json()
        if status["state"] in ("succeeded", "failed", "cancelled"):
            return status
        time.sleep(0.2)
    pytest.fail(f"job {job_id} did not finish in {timeout} s: {status}")


def assert_error(response: httpx.Response, status: int) -> str:
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith("application/json")
    body = response.json()
    assert set(body) == {"detail"} and isinstance(body["detail"], str)
    detail = body["detail"]
    assert detail.endswith(".") and "\n" not in detail and detail[0].isupper()
    return detail
