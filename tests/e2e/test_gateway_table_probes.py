"""Uploaded nuScenes archives with hostile tables, against a real `rangeret serve` process: each is
refused in one sentence naming the table, record and field (a 400, or a job that fails saying so)
in bounded time, nothing is written outside the job's folder, and the gateway's memory comes back
to within 100 MiB of where it was (its peak never 1 GiB above it)."""

from __future__ import annotations

import io
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch
import yaml

from tests.support.gateway import Gateway, gateway_env, start_gateway, wait_job
from tests.support.nuscenes import network, write_tree
from tests.support.table_probes import ESCAPED, PROBES, tree_files

pytestmark = pytest.mark.slow
MIB = 1 << 20
TIMEOUT = 60


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory) -> dict:
    base = tmp_path_factory.mktemp("table-probes")
    tree = write_tree(base / "roots" / "nu", {"scene-0103": 2})
    torch.save(network(0).state_dict(), base / "nu.pt")
    models = base / "models.yaml"
    entry = {"checkpoint": str(base / "nu.pt"), "profile": "nuscenes"}
    models.write_text(yaml.safe_dump({"default": "nu", "models": {"nu": entry}}))
    return {"base": base, "files": tree_files(tree), "models": models}


@pytest.fixture(scope="module")
def gateway(setup: dict) -> Iterator[Gateway]:
    env = gateway_env(setup["base"] / "state", [setup["base"] / "roots"])
    gw = start_gateway(None, env, setup["base"] / "gateway.log", "--models", str(setup["models"]))
    yield gw
    gw.stop()


def _memory(pid: int) -> dict[str, int]:
    """The process's resident memory now (VmRSS) and at its peak (VmHWM), in bytes."""
    fields = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            fields[key] = int(value.split()[0]) * 1024
    return fields


def _upload(files: dict[str, bytes]) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, data in files.items():
            zf.writestr(name, data)
    return buffer.getvalue()


@pytest.mark.parametrize("probe", list(PROBES))
def test_each_hostile_upload_is_refused_in_bounded_time_and_memory(probe, setup, gateway):
    rewrite, expected = PROBES[probe]
    archive = _upload(rewrite(setup["files"]))
    before = _memory(gateway.proc.pid)
    start = time.monotonic()
    with gateway.client(timeout=TIMEOUT) as client:
        answer = client.post(
            "/v1/jobs/uploads", files={"archive": ("nu.zip", archive, "application/zip")}
        )
        if answer.status_code == 400:
            reason = answer.json()["detail"]
        else:
            assert answer.status_code == 202, answer.text
            job = wait_job(client, answer.json()["id"], timeout=TIMEOUT)
            assert job["state"] == "failed", job
            reason = job["error"]
    assert time.monotonic() - start < TIMEOUT
    assert expected in reason and "\n" not in reason, reason
    after = _memory(gateway.proc.pid)
    assert after["VmHWM"] - before["VmRSS"] < 1024 * MIB, (before, after)
    assert after["VmRSS"] - before["VmRSS"] < 100 * MIB, (before, after)
    assert not list(setup["base"].rglob(f"*{ESCAPED}"))
    assert not Path("/tmp/escaped_lidarseg.bin").exists()
    assert gateway.proc.poll() is None
