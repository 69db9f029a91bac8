"""A benchmark from outside the library (`tests.support.toy_benchmark`), registered as the docs
say (an entry point of `rangeret.benchmarks`), runs through `rangeret evaluate`, `submission`,
`validate-submission`, `python -m workers.predict_job` on a local Ray and a gateway dataset job
in a real `rangeret serve` process, without a line of the library changed for it."""

from __future__ import annotations

import io
import json
import os
import zipfile
from pathlib import Path

import pytest
import torch
import yaml

from rangeret.cli.main import main as rangeret_main
from rangeret.dataset.profiles import load_profile
from rangeret.models import build_model, save_checkpoint
from rangeret.sim import simulate_dataset
from rangeret.submission.benchmarks import benchmark_of, registered
from tests.support.gateway import gateway_env, start_gateway, wait_job
from tests.support.toy_benchmark import ToyBenchmark, register
from workers.predict_job import main as job_main

pytestmark = pytest.mark.slow


@pytest.fixture
def toy(tmp_path, monkeypatch):
    """The toy benchmark registered, a profile naming it (PandaSet's sensor at 32 x 256 with
    sequence 001 for validation and 002 for test), a network for it and a simulated tree."""
    dist = register(tmp_path / "dist")
    monkeypatch.syspath_prepend(str(dist))
    registered.cache_clear()
    data = load_profile("pandaset").with_overrides(height=32, width=256).to_dict()
    data["name"] = "toy-panda"
    data["benchmark"]["name"] = "toy"
    data["splits"] = {"train": ["003"], "valid": ["001"], "test": ["002"]}
    profile_file = tmp_path / "toy.yaml"
    profile_file.write_text(yaml.safe_dump(data, sort_keys=False))
    profile = load_profile(profile_file)
    torch.manual_seed(0)
    weights = tmp_path / "toy.pt"
    network = build_model("rangeret-cir", 32, 256, num_classes=profile.num_classes, layers=1)
    save_checkpoint(weights, network, profile=profile.to_dict())
    root = tmp_path / "roots" / "toy"
    simulate_dataset(root, {"1": 2, "2": 1}, labelled=["1"], seed=3, profile=profile)
    yield {"dist": dist, "profile_file": profile_file, "weights": weights, "root": root}
    registered.cache_clear()


def _members(archive: Path | bytes) -> dict[str, bytes]:
    source = io.BytesIO(archive) if isinstance(archive, bytes) else archive
    with zipfile.ZipFile(source) as zf:
        return {n: zf.read(n) for n in zf.namelist()}


def test_the_toy_benchmark_runs_through_every_runner(toy, tmp_path, capsys, ray_local):
    profile_option = ["--profile", str(toy["profile_file"])]
    assert isinstance(benchmark_of(load_profile(toy["profile_file"])), ToyBenchmark)
    root, pred = toy["root"], tmp_path / "pred"
    common = ["-q", "--checkpoint", str(toy["weights"]), "--device", "cpu"]
    predict = ["predict", "--dataset", str(root), "--sequences", "1", "2", "--out", str(pred)]
    assert rangeret_main([*predict, *common]) == 0

    report = tmp_path / "report.json"
    evaluate = ["evaluate", "-q", "--dataset", str(root), "--predictions", str(pred)]
    assert (
        rangeret_main([*evaluate, "--split", "valid", *profile_option, "--json", str(report)]) == 0
    )
    assert json.loads(report.read_text())["profile"] == "toy-panda"

    archive = tmp_path / "toy.zip"
    submission = ["submission", "-q", "--predictions", str(pred), "--dataset", str(root)]
    code = rangeret_main([*submission, "--out", str(archive), *profile_option, "--toy-note", "hi"])
    assert code == 0, capsys.readouterr().err
    members = _members(archive)
    assert json.loads(members["toy.json"]) == {"scans": 1, "note": "hi"}
    assert (
        members["toy/002/000000.label"]
        == (pred / "sequences/002/predictions/000000.label").read_bytes()
    )

    validate = ["validate-submission", str(archive), "--dataset", str(root), *profile_option]
    assert rangeret_main(validate) == 0
    broken = tmp_path / "broken.zip"
    with zipfile.ZipFile(broken, "w") as zf:
        zf.writestr("toy.json", json.dumps({"scans": 1}))
    assert rangeret_main([*validate[:1], str(broken), *validate[2:]]) == 1
    assert "toy/002/000000.label is missing" in capsys.readouterr().err
    other = [*submission, "--out", str(tmp_path / "x.zip"), *profile_option, "--split", "test"]
    assert rangeret_main(other) == 1
    assert "--split is an option of nuScenes-lidarseg archives" in capsys.readouterr().err

    job_archive = tmp_path / "job.zip"
    job = ["--dataset", str(root), "--sequences", "1", "2", "--out", str(tmp_path / "ray")]
    assert job_main([*job, *common, "--submission", str(job_archive)]) == 0
    assert _members(job_archive)["toy/002/000000.label"] == members["toy/002/000000.label"]


def test_a_gateway_dataset_job_returns_the_toy_benchmarks_zip(toy, tmp_path):
    path = os.pathsep.join([str(toy["dist"]), *filter(None, [os.environ.get("PYTHONPATH")])])
    env = gateway_env(tmp_path / "state", [toy["root"].parent], PYTHONPATH=path)
    gw = start_gateway(toy["weights"], env, tmp_path / "gateway.log")
    try:
        with gw.client() as client:
            r = client.post("/v1/jobs", json={"dataset": "toy", "sequences": ["1", "2"]})
            assert r.status_code == 202, r.text
            status = wait_job(client, r.json()["id"])
            assert status["state"] == "succeeded", status
            served = client.get(f"/v1/jobs/{status['id']}/predictions").content
    finally:
        gw.stop()
    members = _members(served)
    assert sorted(n for n in members if n.startswith("toy/")) == [
        "toy/001/000000.label",
        "toy/001/000001.label",
        "toy/002/000000.label",
    ]
    manifest = json.loads(members["toy.json"])
    assert manifest["scans"] == 3 and len(manifest["sha256"]) == 64
