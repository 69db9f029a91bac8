"""A gateway process for the HTTP benchmarks: `python -m service` on a free loopback port, with
its own RANGERET_* environment and log, started once it answers /healthz and stopped with SIGTERM;
its resident memory; and the single-scan load the benchmarks put on it."""

from __future__ import annotations

import asyncio
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import httpx
from _common import REPO

#: Seconds a gateway may take to load its network and answer /healthz.
START_TIMEOUT_S = 180


def free_port() -> int:
    """A free TCP port on 127.0.0.1."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class StartedGateway:
    """A gateway process a benchmark started, its address and its log."""

    proc: subprocess.Popen
    url: str
    log: Path
    description: str

    def log_tail(self) -> str:
        return self.log.read_text(errors="replace")[-3000:] if self.log.exists() else ""

    def stop(self) -> str:
        """SIGTERM, then wait (SIGKILL after 30 s); how it ended."""
        if self.proc.poll() is not None:
            return f"had already exited with {self.proc.returncode}"
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(10)
            return "did not stop within 30 s of SIGTERM and was killed"
        if self.proc.returncode == -signal.SIGTERM:  # uvicorn re-raises it once shut down
            return "stopped on SIGTERM after its graceful shutdown"
        return f"stopped on SIGTERM, exit code {self.proc.returncode}"


def rss_mib(pid: int | None) -> float | None:
    """The resident set size (VmRSS) of process `pid` in MiB, or None when it cannot be read."""
    if pid is None:
        return None
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def start_gateway(
    options: list[str], settings: dict[str, str], log: Path, description: str
) -> StartedGateway:
    """`python -m service OPTIONS` with the RANGERET_* `settings` (and no other RANGERET_*
    variable of this environment), once it answers /healthz with 200; exits with its log's end
    when it does not."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("RANGERET_")}
    env.update(settings)
    port = free_port()
    cmd = [sys.executable, "-m", "service", *options, "--port", str(port), "--log-level", "warning"]
    with open(log, "wb") as out:
        proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT)
    gw = StartedGateway(proc, f"http://127.0.0.1:{port}", log, description)
    deadline = time.time() + START_TIMEOUT_S
    while time.time() < deadline:
        if proc.poll() is not None:
            sys.exit(f"the gateway exited with {proc.returncode}:\n{gw.log_tail()}")
        try:
            if httpx.get(gw.url + "/healthz", timeout=2).status_code == 200:
                return gw
        except httpx.TransportError:
            pass
        time.sleep(0.2)
    gw.stop()
    sys.exit(f"the gateway did not answer /healthz within {START_TIMEOUT_S} s:\n{gw.log_tail()}")


OCTET = {"Content-Type": "application/octet-stream"}


async def load(
    url: str, body: bytes, clients: int, scans: int, timeout: float = 600, warmup: int = 2
) -> tuple[float, list[float]]:
    """Wall time and per-request latencies of `clients` clients each sending `scans` requests
    one after another (after `warmup` requests that are not counted)."""
    latencies: list[float] = []
    limits = httpx.Limits(max_connections=clients)
    async with httpx.AsyncClient(base_url=url, timeout=timeout, limits=limits) as client:

        async def one_client() -> None:
            for _ in range(scans):
                start = time.perf_counter()
                answer = await client.post("/v1/scans", content=body, headers=OCTET)
                answer.raise_for_status()
                latencies.append(time.perf_counter() - start)

        for _ in range(warmup):
            (await client.post("/v1/scans", content=body, headers=OCTET)).raise_for_status()
        start = time.perf_counter()
        await asyncio.gather(*(one_client() for _ in range(clients)))
        return time.perf_counter() - start, latencies
