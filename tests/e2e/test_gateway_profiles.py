"""The gateway serving a PandaSet network, against a real uvicorn process on 127.0.0.1.

Single scans are 5-float records (x, y, z, intensity, laser_id) labelled with PandaSet's raw ids
as `rangeret predict --profile pandaset` labels them; bodies that are not whole 20-byte records
and laser ids off the image are 400s; `/healthz` and `/metrics` name the profile; dataset and
archive jobs read the PandaSet layout (ROOT/NNN); and a network whose class count is not the
profile's stops `rangeret serve` with one line.
"""

from __future__ import annotations

import io
import subprocess
import sys
import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

from rangeret.cli.main import main as rangeret_main
from rangeret.dataset.layout import prediction_path
from rangeret.dataset.profiles import load_profile
from rangeret.io.scans import read_labels, read_scan
from rangeret.models import build_model
from rangeret.sim import simulate_dataset
from tests.support.gateway import (
    Gateway,
    assert_error,
    free_port,
    gateway_env,
    start_gateway,
    wait_job,
)
from tests.support.paths import REPO
from tests.support.workers import small_weights

OCTET = {"Content-Type": "application/octet-stream"}
PROFILE = ["--profile", "pandaset"]


@pytest.fixture(scope="module")
def panda(tmp_path_factory) -> dict:
    """A 15-class published-format state_dict at 32 x 256, a simulated PandaSet tree (001
    labelled, 002 not) under a data root, and `rangeret predict --profile pandaset` on it."""
    base = tmp_path_factory.mktemp("pandaset-gateway")
    torch.manual_seed(0)
    weights = base / "pandaset-small.pt"
    torch.save(build_model("rangeret-cir", 32, 256, num_classes=15, layers=1).state_dict(), weights)
    roots = base / "roots"
    profile = load_profile("pandaset").with_overrides(height=32, width=256)
    simulate_dataset(roots / "panda", {"1": 2, "2": 1}, labelled=["1"], seed=5, profile=profile)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        args = ["predict", "--dataset", str(roots / "panda"), "--sequences", "1", "2"]
        args += ["--out", str(base / "ref"), "--checkpoint", str(weights), *PROFILE, "-q"]
        assert rangeret_main([*args, "--height", "32", "--width", "256", "--device", "cpu"]) == 0
    finally:
        torch.set_num_threads(threads)
    return {"base": base, "weights": weights, "roots": roots, "ref": base / "ref"}


@pytest.fixture(scope="module")
def gateway(panda) -> Iterator[Gateway]:
    env = gateway_env(panda["base"] / "state", [panda["roots"]])
    gw = start_gateway(panda["weights"], env, panda["base"] / "gateway.log", *PROFILE)
    yield gw
    gw.stop()


def _scan(panda: dict, seq: str = "001", name: str = "000000") -> Path:
    return panda["roots"] / "panda" / seq / "velodyne" / f"{name}.bin"  # PandaSet: ROOT/NNN


def test_a_pandaset_scan_gets_pandaset_labels_as_rangeret_predict_does(panda, gateway):
    body = _scan(panda).read_bytes()
    labels = load_profile("pandaset").labels
    with gateway.client() as client:
        raw = client.post("/v1/scans", content=body, headers=OCTET)
        as_json = client.post(
            "/v1/scans", content=body, headers={**OCTET, "Accept": "application/json"}
        )
    assert raw.status_code == 200, raw.text
    assert raw.content == prediction_path(panda["ref"], "001", "000000").read_bytes()
    assert len(raw.content) == len(body) // 20 * 4
    found = np.frombuffer(raw.content, dtype="<u4")
    assert set(found.tolist()) <= set(labels.raw_to_class)
    answer = as_json.json()
    assert answer["num_points"] == len(body) // 20 and answer["labels"] == found.tolist()
    assert set(answer["class_counts"]) <= set(labels.class_names)
    assert sum(answer["class_counts"].values()) == answer["num_points"]


def test_bodies_are_pandaset_records(panda, gateway):
    points = read_scan(_scan(panda), load_profile("pandaset").points)
    four = points[:7, :4].tobytes()  # 112 bytes: whole 16-byte records, not 20-byte ones
    off_image = points[:50].copy()
    off_image[3, 4] = 40  # the image has rows 0..31
    with gateway.client() as client:
        detail = assert_error(client.post("/v1/scans", content=four, headers=OCTET), 400)
        assert "20 bytes per point" in detail and "laser_id" in detail, detail
        detail = assert_error(
            client.post("/v1/scans", content=off_image.tobytes(), headers=OCTET), 400
        )
        assert "laser id" in detail and "0..31" in detail, detail
        many = np.ones((200_001, 5), dtype=np.float32).tobytes()
        assert "200,000" in assert_error(client.post("/v1/scans", content=many, headers=OCTET), 413)
        ok = client.post("/v1/scans", content=points[:50].tobytes(), headers=OCTET)
        assert ok.status_code == 200 and len(ok.content) == 200


def test_healthz_and_metrics_name_the_profile(gateway):
    with gateway.client(auth=False) as client:
        summary = client.get("/healthz").json()
        metrics = client.get("/metrics").text
        description = client.get("/openapi.json").json()["info"]["description"]
    with gateway.client() as client:
        health = client.get("/healthz").json()
    assert summary["profile"] == health["profile"] == "pandaset"
    assert health["point_fields"] == ["x", "y", "z", "intensity", "laser_id"]
    assert 'rangeret_gateway_info{profile="pandaset"} 1.0' in metrics
    assert "`pandaset`" in description and "20 bytes per point" in description


def test_a_dataset_job_reads_the_pandaset_layout(panda, gateway):
    with gateway.client() as client:
        other = client.post(
            "/v1/jobs",
            json={"dataset": "panda", "sequences": ["1"], "profile": "semantickitti"},
        )
        detail = assert_error(other, 400)
        assert "'semantickitti'" in detail and "'pandaset'" in detail, detail
        r = client.post(
            "/v1/jobs", json={"dataset": "panda", "sequences": ["1", "2"], "profile": "pandaset"}
        )
        assert r.status_code == 202, r.text
        status = wait_job(client, r.json()["id"])
        assert status["state"] == "succeeded", status
        assert status["sequences"] == ["001", "002"]
        assert (status["total"], status["done"], status["failed"]) == (3, 3, 0)
        report = client.get(f"/v1/jobs/{status['id']}/report").json()
        archive = client.get(f"/v1/jobs/{status['id']}/predictions").content
    assert report["profile"] == "pandaset" and report["num_scans"] == 2
    assert set(status["metrics"]["iou"]) <= set(load_profile("pandaset").labels.class_names)
    with zipfile.ZipFile(io.BytesIO(archive)) as zf:
        served = {n: zf.read(n) for n in zf.namelist() if n.endswith(".label")}
        assert "profile: pandaset" in zf.read("description.txt").decode()
    expected = {
        p.relative_to(panda["ref"]).as_posix(): p.read_bytes()
        for p in panda["ref"].rglob("*.label")
    }
    assert served == expected and len(served) == 3


def test_an_archive_job_holds_pandaset_records(panda, gateway):
    def zipped(members: dict[str, bytes]) -> bytes:
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w") as zf:
            for name, data in members.items():
                zf.writestr(name, data)
        return buf.getvalue()

    scan = _scan(panda, "001", "000001")
    good = zipped(
        {
            "sequences/001/velodyne/000001.bin": scan.read_bytes(),
            "sequences/001/labels/000001.label": (
                scan.parent.parent / "labels" / "000001.label"
            ).read_bytes(),
        }
    )
    bad = zipped({"sequences/001/velodyne/000000.bin": b"\0" * 16 * 7})
    with gateway.client() as client:
        detail = assert_error(
            client.post("/v1/jobs", files={"archive": ("bad.zip", bad, OCTET["Content-Type"])}),
            400,
        )
        assert "multiple of 20" in detail and "laser_id" in detail, detail
        r = client.post("/v1/jobs", files={"archive": ("data.zip", good, OCTET["Content-Type"])})
        assert r.status_code == 202, r.text
        status = wait_job(client, r.json()["id"])
        archive = client.get(f"/v1/jobs/{status['id']}/predictions").content
    assert status["state"] == "succeeded" and status["metrics"] is not None, status
    with zipfile.ZipFile(io.BytesIO(archive)) as zf:
        served = zf.read("sequences/001/predictions/000001.label")
    assert served == prediction_path(panda["ref"], "001", "000001").read_bytes()
    assert read_labels(prediction_path(panda["ref"], "001", "000001")).size == len(served) // 4


def test_serve_refuses_a_network_with_another_class_count(tmp_path):
    weights = small_weights(tmp_path)  # 19 classes, SemanticKITTI's
    cmd = [
        str(Path(sys.executable).with_name("rangeret")),
        "serve",
        "--checkpoint",
        str(weights),
        *PROFILE,
        "--height",
        "32",
        "--width",
        "256",
        "--device",
        "cpu",
        "--port",
        str(free_port()),
    ]
    env = gateway_env(tmp_path / "state", [tmp_path])
    run = subprocess.run(
        cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=120, check=False
    )
    assert run.returncode == 1, run.stderr
    lines = run.stderr.strip().splitlines()
    assert "Traceback" not in run.stderr and len(lines) == 1, run.stderr
    assert "predicts 20 classes" in lines[0] and "pandaset profile has 15" in lines[0], lines[0]
