"""`python -m workers.predict_job --inference-spec JSON`: the spec a gateway submits as one
option, checked by name before anything starts, and its checkpoint read once per process (the
driver once, each model actor once)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from rangeret.cli.main import main as rangeret_main
from tests.support.open_audit import Audit
from tests.support.paths import REPO
from tests.support.workers import build_tree, small_weights, tree_bytes


def _job(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "workers.predict_job", "-q", *args],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )


@pytest.mark.slow
def test_the_job_reads_its_checkpoint_once_in_the_driver_and_in_each_model_actor(tmp_path):
    weights = small_weights(tmp_path)
    data = build_tree(tmp_path / "data", labelled=2, unlabelled=1)
    spec = {"checkpoint": str(weights), "height": 32, "width": 256, "device": "cpu"}
    spec["batch_size"] = 2
    net = ["--checkpoint", str(weights), "--height", "32", "--width", "256", "--device", "cpu"]
    argv = ["predict", "-q", "--dataset", str(data), "--sequences", "08", "11"]
    out = tmp_path / "single"
    assert rangeret_main([*argv, "--out", str(out), *net, "--batch-size", "2"]) == 0

    audit = Audit(tmp_path / "audit.log", (weights.name,))
    selection = ["--dataset", str(data), "--sequences", "08", "11", "--actors", "2"]
    run = _job(
        *selection,
        *("--out", str(tmp_path / "ray"), "--inference-spec", json.dumps(spec)),
        env=audit.env(),
    )
    assert run.returncode == 0, run.stderr[-3000:]
    assert tree_bytes(tmp_path / "ray") == tree_bytes(out)
    reads = audit.reads()
    assert set(reads.values()) == {1} and len(reads) == 3, audit.lines()  # driver + 2 actors


@pytest.mark.parametrize(
    ("spec", "extra", "sentence"),
    [
        ('{"batch_size": "eight"}', [], "batch_size in --inference-spec takes an integer"),
        ('{"bogus": 1}', [], "unknown network option bogus in --inference-spec"),
        ("[1]", [], "--inference-spec must be a JSON object, got list"),
        ("{", [], "--inference-spec is not JSON"),
        ("{}", ["--batch-size", "4"], "--inference-spec holds every network option: give"),
        ('{"a":' * 3000 + "1" + "}" * 3000, [], "--inference-spec nests deeper than"),
    ],
)
def test_a_bad_inference_spec_is_one_sentence_before_anything_starts(
    tmp_path, spec, extra, sentence
):
    run = _job(
        *("--dataset", str(tmp_path), "--sequences", "08", "--out", str(tmp_path / "out")),
        *("--inference-spec", spec, *extra),
    )
    assert run.returncode == 1 and "Traceback" not in run.stderr, run.stderr
    assert sentence in run.stderr
    assert not (tmp_path / "out").exists()
