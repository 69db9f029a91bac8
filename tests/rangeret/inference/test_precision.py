"""Precision as a choice: fp32, fp16 and bf16 forward passes, recorded with every run."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from rangeret.cli.main import main
from rangeret.inference.predictor import Predictor
from rangeret.inference.runtime.precision import PRECISIONS, forward_precision, resolve_precision
from rangeret.io.scans import read_scan
from rangeret.models.weights.demo import DEMO_CHECKPOINT
from tests.support.trees import make_tree


def test_auto_is_fp16_on_cuda_and_fp32_on_the_cpu():
    assert resolve_precision("auto", torch.device("cpu")) == "fp32"
    assert resolve_precision("auto", torch.device("cuda")) == "fp16"
    for name in ("fp32", "fp16", "bf16"):
        assert resolve_precision(name, torch.device("cpu")) == name
    with pytest.raises(ValueError, match="--precision must be one of auto, fp32, fp16, bf16"):
        resolve_precision("fp8", torch.device("cpu"))
    assert PRECISIONS == ("auto", "fp32", "fp16", "bf16")


@pytest.mark.parametrize(
    ("precision", "dtype"), [("bf16", torch.bfloat16), ("fp16", torch.float16)]
)
def test_reduced_precisions_run_the_matmuls_in_their_dtype(precision, dtype):
    layer = torch.nn.Linear(8, 4)
    with forward_precision(precision, torch.device("cpu")):
        assert layer(torch.ones(2, 8)).dtype == dtype
    with forward_precision("fp32", torch.device("cpu")):
        assert layer(torch.ones(2, 8)).dtype == torch.float32


def test_fp32_on_cuda_turns_tf32_off_for_the_pass_only():
    torch.backends.cudnn.allow_tf32 = True
    with forward_precision("fp32", torch.device("cuda")):
        assert not torch.backends.cudnn.allow_tf32 and not torch.backends.cuda.matmul.allow_tf32
    assert torch.backends.cudnn.allow_tf32


@pytest.fixture(scope="module")
def demo_scan(real_scan_path):
    return read_scan(real_scan_path)


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_the_same_precision_gives_the_same_labels(precision, demo_scan):
    """Same weights, precision, batch size and device type: identical labels, run after run."""
    first = Predictor.from_checkpoint(DEMO_CHECKPOINT, device="cpu", precision=precision)
    second = Predictor.from_checkpoint(DEMO_CHECKPOINT, device="cpu", precision=precision)
    assert first.precision == precision
    a, b = first.predict(demo_scan).labels, second.predict(demo_scan).labels
    assert np.array_equal(a, b)


def test_bf16_agrees_with_fp32_on_most_points(demo_scan):
    fp32 = Predictor.from_checkpoint(DEMO_CHECKPOINT, device="cpu", precision="fp32")
    bf16 = Predictor.from_checkpoint(DEMO_CHECKPOINT, device="cpu", precision="bf16")
    a, b = fp32.predict(demo_scan).labels, bf16.predict(demo_scan).labels
    assert a.shape == b.shape and (a == b).mean() > 0.9


def test_the_run_records_its_precision(tmp_path, capsys):
    make_tree(tmp_path / "data", {"08": [300]})
    args = ["predict", "-q", "--dataset", str(tmp_path / "data"), "--sequences", "08"]
    assert (
        main([*args, "--out", str(tmp_path / "a"), "--precision", "bf16", "--device", "cpu"]) == 0
    )
    assert json.loads((tmp_path / "a" / "run.json").read_text())["precision"] == "bf16"
    assert main([*args, "--out", str(tmp_path / "b"), "--device", "cpu"]) == 0
    assert json.loads((tmp_path / "b" / "run.json").read_text())["precision"] == "fp32"
    with pytest.raises(SystemExit):
        main([*args, "--out", str(tmp_path / "c"), "--precision", "fp64"])
    assert "invalid choice: 'fp64'" in capsys.readouterr().err
