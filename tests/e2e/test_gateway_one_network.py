"""The in-process gateway holds one network: `python -m service` reads its checkpoint once for
single scans and jobs alike, and imports no module of the Ray layer while it labels and runs a
job."""

from __future__ import annotations

import io
import zipfile

import pytest

from rangeret.cli.main import main as rangeret_main
from rangeret.dataset.layout import prediction_path
from tests.support.gateway import NET, OCTET, gateway_env, start_gateway, wait_job
from tests.support.open_audit import Audit
from tests.support.workers import build_tree, small_weights


@pytest.mark.slow
def test_one_scan_and_one_job_share_the_one_read_of_the_checkpoint(tmp_path):
    weights = small_weights(tmp_path)
    data = build_tree(tmp_path / "data", labelled=1, unlabelled=1)
    reference = tmp_path / "reference"
    argv = ["predict", "-q", "--dataset", str(data), "--sequences", "08", "11"]
    assert rangeret_main([*argv, "--out", str(reference), "--checkpoint", str(weights), *NET]) == 0

    audit = Audit(tmp_path / "audit.log", (weights.name,))
    env = audit.env(gateway_env(tmp_path / "state", [tmp_path]))
    gateway = start_gateway(weights, env, tmp_path / "gateway.log")
    try:
        scan = data / "sequences" / "08" / "velodyne" / "000000.bin"
        buffer = io.BytesIO()
        with zipfile.ZipFile(buffer, "w") as archive:
            for path in sorted(data.rglob("*")):
                if path.is_file():
                    archive.write(path, path.relative_to(data).as_posix())
        with gateway.client() as client:
            answer = client.post("/v1/scans", content=scan.read_bytes(), headers=OCTET)
            assert answer.status_code == 200, answer.text
            assert answer.content == prediction_path(reference, "08", "000000").read_bytes()
            upload = ("data.zip", buffer.getvalue(), "application/octet-stream")
            job = client.post("/v1/jobs", files={"archive": upload})
            assert job.status_code == 202, job.text
            status = wait_job(client, job.json()["id"])
            assert status["state"] == "succeeded", status
            again = client.post("/v1/scans", content=scan.read_bytes(), headers=OCTET)
            assert again.content == answer.content
            health = client.get("/healthz").json()
    finally:
        gateway.stop()
    pid = gateway.proc.pid
    assert audit.reads() == {pid: 1}, audit.lines()
    assert audit.imports(pid) == []
    assert [w["pid"] for w in health["workers"]] == [pid]
