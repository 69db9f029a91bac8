"""End to end: `ray job submit` of workers.predict_job to a head started with `ray start --head`
(token authentication), producing a predictions tree and an archive the validator accepts."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from workers_helpers import build_tree, small_weights

from rangeret.submission import validate_submission

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parent.parent
EXCLUDES = [".venv", ".git", "runs", "__pycache__", ".pytest_cache", ".ruff_cache", "*.egg-info"]


def _free_ports(n: int) -> list[int]:
    socks, ports = [], []
    for _ in range(n):
        s = socket.socket()
        s.bind(("127.0.0.1", 0))
        socks.append(s)
        ports.append(s.getsockname()[1])
    for s in socks:
        s.close()
    return ports


@pytest.fixture
def head(tmp_path_factory):
    """A Ray head of its own (own ports, own temp folder), stopped with its whole process group."""
    bindir = Path(sys.executable).parent
    env = dict(os.environ, PATH=f"{bindir}{os.pathsep}{os.environ['PATH']}", RAY_AUTH_MODE="token")
    temp = Path(f"/tmp/rr-{os.getpid()}")
    gcs, dash, client, agent, grpc, metrics, nm, om, wmin = _free_ports(9)
    cmd = [
        str(bindir / "ray"), "start", "--head", "--block", "--num-cpus", "2", "--port", str(gcs),
        "--include-dashboard", "true", "--dashboard-host", "127.0.0.1", "--dashboard-port", str(dash),
        "--ray-client-server-port", str(client), "--dashboard-agent-listen-port", str(agent),
        "--dashboard-agent-grpc-port", str(grpc), "--metrics-export-port", str(metrics),
        "--node-manager-port", str(nm), "--object-manager-port", str(om),
        "--min-worker-port", str(wmin), "--max-worker-port", str(wmin + 40), "--temp-dir", str(temp),
        "--disable-usage-stats",
    ]
    log = open(tmp_path_factory.mktemp("head") / "head.log", "w")  # noqa: SIM115
    proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    address = f"http://127.0.0.1:{dash}"
    deadline = time.time() + 120
    while time.time() < deadline:
        probe = subprocess.run([str(bindir / "ray"), "job", "list", "--address", address],
                               env=env, capture_output=True, text=True, check=False)
        if probe.returncode == 0:
            break
        if proc.poll() is not None:
            pytest.fail(f"ray start --head exited with {proc.returncode}; see {log.name}")
        time.sleep(1)
    else:
        pytest.fail(f"the head's job server did not answer in 120 s; see {log.name}")
    yield address, env, bindir
    os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
    log.close()
    shutil.rmtree(temp, ignore_errors=True)


def test_ray_job_submit_writes_a_valid_archive(head, tmp_path):
    address, env, bindir = head
    data = build_tree(tmp_path / "data", labelled=2, unlabelled=3)
    weights = small_weights(tmp_path)
    out, archive, report = tmp_path / "pred", tmp_path / "submission.zip", tmp_path / "report.json"
    cmd = [
        str(bindir / "ray"), "job", "submit", "--address", address, "--working-dir", str(REPO),
        "--runtime-env-json", json.dumps({"excludes": EXCLUDES}),
        "--", "python", "-m", "workers.predict_job", "--dataset", str(data), "--sequences", "08", "11",
        "--out", str(out), "--submission", str(archive), "--allow-partial", "--report", str(report),
        "--checkpoint", str(weights), "--height", "32", "--width", "256", "--read-cpus", "0.25",
    ]
    run = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, check=False)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    assert "5 written" in run.stdout
    check = validate_submission(archive, data, allow_partial=True)
    assert check.ok and check.scans == 3
    assert json.loads(report.read_text())["num_scans"] == 2
    assert len(list(out.rglob("*.label"))) == 5
