"""`benchmarks/gpu_check.py`: the smoke run on the CPU without Ray, FastAPI or pydantic, the JSON
after every section, time budgets, and failures recorded without stopping the run."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
import torch

from tests.support.paths import REPO
from tests.support.scripts import load_benchmark

gpu_check = load_benchmark("gpu_check")

SCRIPT = REPO / "benchmarks" / "gpu_check.py"
BLOCKED = ("ray", "fastapi", "pydantic", "pydantic_settings", "uvicorn", "starlette")
#: Runs a script with the named modules made unimportable (None in sys.modules).
RUNNER = """\
import os, runpy, sys
for name in sys.argv[1].split(","):
    sys.modules[name] = None
script = sys.argv[2]
sys.argv = sys.argv[2:]
sys.path.insert(0, os.path.dirname(script))
runpy.run_path(script, run_name="__main__")
"""


def fraction(value: float) -> bool:
    return 0.0 <= value <= 1.0


@pytest.fixture(scope="module")
def smoke(tmp_path_factory) -> tuple[subprocess.CompletedProcess, dict]:
    out = tmp_path_factory.mktemp("gpu-check")
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    run = subprocess.run(
        [
            sys.executable,
            "-c",
            RUNNER,
            ",".join(BLOCKED),
            str(SCRIPT),
            "--smoke",
            "--out",
            str(out),
        ],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    path = out / "gpu_check.json"
    assert path.exists(), run.stdout[-3000:] + run.stderr[-3000:]
    return run, json.loads(path.read_text())


@pytest.mark.slow
def test_smoke_runs_every_section_without_ray_fastapi_or_pydantic(smoke):
    run, doc = smoke
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    sections = doc["sections"]
    assert list(sections) == list(gpu_check.SECTIONS)
    assert doc["complete"] and doc["mode"] == "smoke"
    for name, section in sections.items():
        assert section["status"] in ("ok", "skipped"), (name, section)
        assert isinstance(section["seconds"], float) and section["seconds"] >= 0
    assert "gpu check (smoke): 6 ok, 0 failed" in run.stdout

    env = sections["environment"]
    assert env["ray_importable"] is False and "not importable" in env["ray_reason"]
    assert env["torch"] == torch.__version__ and env["cpu_count"] >= 1

    tests = sections["tests"]
    assert tests["returncode"] == 0 and tests["counts"]["failed"] == 0
    if not torch.cuda.is_available():
        assert tests["counts"]["skipped"] >= 1 and tests["counts"]["passed"] == 0

    correctness = sections["correctness"]
    assert correctness["published_fp32"]["max_abs_error"] < 1e-3
    for precision in ("fp16", "bf16"):
        figures = correctness["precisions"][precision]
        assert figures["finite"] and fraction(figures["argmax_agreement"])
        assert figures["max_abs_error"] < figures["max_abs_fp32_logit"]
    assert correctness["batch_vs_single"]["max_abs_difference"] < 1e-3
    assert fraction(correctness["batch_vs_single"]["argmax_agreement"])
    for network in gpu_check.NETWORKS:
        assert correctness["cpu_vs_device_labels"][network]["labels_equal"] == 1.0

    runs = sections["throughput"]["runs"]
    assert len(runs) == len(gpu_check.NETWORKS) * len(gpu_check.PRECISIONS) * 2
    assert all(r["scans_per_s"] > 0 and r["median_ms"] > 0 and r["finite"] for r in runs)

    assert sections["knn"]["labels_equal"] == 1.0 and sections["knn"]["points"] == 123_389

    pipeline = sections["pipeline"]
    assert pipeline["in_process"]["written"] == pipeline["scans"] == 6
    assert pipeline["in_process"]["steady_state"]["scans_per_s"] > 0
    assert pipeline["ray"]["status"] == "skipped" and pipeline["ray"]["reason"]


def test_json_is_whole_after_every_section_and_a_failure_stops_nothing(tmp_path, monkeypatch):
    written: list[dict] = []
    real_write = gpu_check.atomic_write_text

    def recording(path, text):
        written.append(json.loads(text))
        real_write(path, text)

    def failing_check(ctx, figures):
        figures["value"] = 2.0
        gpu_check.add_check(figures, "value at most 1", figures["value"] <= 1, "2.0 above 1")

    monkeypatch.setattr(gpu_check, "atomic_write_text", recording)
    monkeypatch.setattr(gpu_check, "REAL_SCAN", tmp_path / "missing.bin")
    sections = {
        "knn": gpu_check.SECTIONS["knn"],
        "checked": gpu_check.Section(failing_check, budget_s=10, needs_s=0),
        "environment": gpu_check.SECTIONS["environment"],
    }
    ctx = gpu_check.Context(plan=gpu_check.smoke_plan(), out=tmp_path, max_seconds=60)
    doc = gpu_check.run_sections(ctx, sections)

    knn = doc["sections"]["knn"]
    assert knn["status"] == "failed" and "missing.bin" in knn["error"]
    assert "\n" not in knn["error"] and knn["traceback"] and isinstance(knn["seconds"], float)
    checked = doc["sections"]["checked"]
    assert checked["status"] == "failed" and checked["error"] == "value at most 1: 2.0 above 1"
    assert checked["value"] == 2.0
    assert doc["sections"]["environment"]["status"] == "ok"
    assert json.loads((tmp_path / "gpu_check.json").read_text()) == doc

    order = list(sections)
    finished = [[n for n, s in w["sections"].items() if s["status"] != "running"] for w in written]
    assert all(f == order[: len(f)] for f in finished)  # results arrive in order, none lost
    assert {len(f) for f in finished} == {0, 1, 2, 3}  # the file was whole after every section
    for name in order:  # and each section was saved as running before its result
        assert any(w["sections"].get(name, {}).get("status") == "running" for w in written)
    assert not written[0]["complete"] and written[-1]["complete"]


def test_a_tiny_time_budget_skips_sections_with_the_budget_as_reason(tmp_path):
    ctx = gpu_check.Context(plan=gpu_check.smoke_plan(), out=tmp_path, max_seconds=0)
    doc = gpu_check.run_sections(ctx, gpu_check.SECTIONS)
    sections = json.loads((tmp_path / "gpu_check.json").read_text())["sections"]
    assert sections == doc["sections"] and list(sections) == list(gpu_check.SECTIONS)
    assert sections["environment"]["status"] == "ok"
    for name in list(sections)[1:]:
        assert sections[name]["status"] == "skipped"
        assert sections[name]["reason"].startswith("time budget: 0 s left of --max-seconds 0")


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the run on a machine without CUDA")
def test_without_smoke_or_cuda_only_the_environment_is_written(tmp_path, capsys):
    assert gpu_check.main(["--out", str(tmp_path)]) == 2
    doc = json.loads((tmp_path / "gpu_check.json").read_text())
    assert list(doc["sections"]) == ["environment"] and doc["mode"] == "device"
    assert "no CUDA device" in capsys.readouterr().err
