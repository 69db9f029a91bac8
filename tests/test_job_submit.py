"""End to end: `ray job submit` of workers.predict_job to a head started with `ray start --head`
(token authentication), producing a predictions tree and an archive the validator accepts."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
from workers_helpers import build_tree, ray_node, small_weights

from rangeret.submission import validate_submission

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parent.parent
EXCLUDES = [".venv", ".git", "runs", "__pycache__", ".pytest_cache", ".ruff_cache", "*.egg-info"]


@pytest.fixture
def head(tmp_path_factory):
    """A Ray head of its own (own ports, own temp folder), stopped with its whole process group."""
    with ray_node(tmp_path_factory.mktemp("head")) as node:
        yield node.dashboard, node.env, node.bindir


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
