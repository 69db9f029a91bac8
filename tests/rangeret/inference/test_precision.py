"""Precision as a choice: fp32, fp16 and bf16 forward passes, what `auto` picks on which CPU or
GPU and why, the fp32 default, and the choice recorded with every run."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging

import numpy as np
import pytest
import torch

from rangeret.cli.main import main
from rangeret.inference.network_fields import PRECISION, TRAINING_PRECISION, option_help
from rangeret.inference.predictor import Predictor
from rangeret.inference.runtime import cpu_features
from rangeret.inference.runtime.precision import (
    PRECISIONS,
    PrecisionChoice,
    auto_choice,
    choose_precision,
    forward_precision,
    precision_reason,
    resolve_precision,
    resolved_reason,
)
from rangeret.inference.spec import InferenceSpec
from rangeret.io.scans import read_scan
from rangeret.models.weights.demo import DEMO_CHECKPOINT
from rangeret.training.config import TrainConfig
from tests.support.trees import make_tree


def _cpu_with(monkeypatch, *flags: str) -> None:
    """Make this process see a CPU with `flags` only."""
    monkeypatch.setattr(cpu_features, "_cpuinfo", lambda: ("Test CPU", frozenset(flags)))


def _cuda(monkeypatch, available: bool, native_bf16: bool = False) -> list[bool]:
    """Make torch see one CUDA device (an A100 with native bf16, or a T4 without) or none; the
    list returned gathers the `including_emulation` of each question about bf16."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: available)
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 0)
    monkeypatch.setattr(
        torch.cuda, "get_device_name", lambda i=None: "A100" if native_bf16 else "T4"
    )
    monkeypatch.setattr(
        torch.cuda, "get_device_capability", lambda i=None: (8, 0) if native_bf16 else (7, 5)
    )
    monkeypatch.setattr(torch.cuda, "device", lambda i: contextlib.nullcontext())
    seen = []

    def supported(including_emulation: bool = True) -> bool:
        seen.append(including_emulation)
        return native_bf16 or including_emulation

    monkeypatch.setattr(torch.cuda, "is_bf16_supported", supported)
    return seen


@pytest.mark.parametrize(
    ("flags", "picked", "because"),
    [
        (("amx_bf16", "amx_tile", "avx512_bf16"), "bf16", "AMX bf16 (amx_bf16)"),
        (("avx512_bf16", "avx512_vnni"), "bf16", "AVX-512 bf16 (avx512_bf16)"),
        (("avx512_vnni", "avx_vnni", "avx2"), "fp32", "neither AMX bf16"),
        ((), "fp32", "neither AMX bf16 (amx_bf16) nor AVX-512 bf16 (avx512_bf16)"),
    ],
)
def test_auto_on_the_cpu_is_bf16_with_amx_or_avx512_bf16(monkeypatch, flags, picked, because):
    _cpu_with(monkeypatch, *flags)
    choice = auto_choice(torch.device("cpu"))
    assert choice.precision == picked and because in choice.reason
    assert resolve_precision("auto", torch.device("cpu")) == picked
    assert choose_precision("auto", "cpu") == PrecisionChoice(
        picked, f"auto's pick here: {choice.reason}"
    )
    other = "fp32" if picked == "bf16" else "bf16"
    assert precision_reason(other, "cpu") == (
        f"asked for{' (fp32 is the default)' if other == 'fp32' else ''}; auto would pick "
        f"{picked} here: {choice.reason}"
    )


def test_auto_on_cuda_is_bf16_where_the_device_runs_it_natively(monkeypatch):
    _cpu_with(monkeypatch, "amx_bf16")
    a100 = _cuda(monkeypatch, available=True, native_bf16=True)
    assert resolve_precision("auto", torch.device("cuda")) == "bf16"
    assert auto_choice("cuda:0").reason == "A100 runs bf16 natively"
    t4 = _cuda(monkeypatch, available=True, native_bf16=False)
    # a T4 emulates bf16: torch says it supports it, but not natively
    assert resolve_precision("auto", torch.device("cuda")) == "fp32"
    assert auto_choice("cuda").reason == "T4 (compute capability 7.5) has no native bf16"
    assert a100 and t4 and not any(a100 + t4), "asked about native support only"
    _cuda(monkeypatch, available=False)
    assert auto_choice("cuda") == PrecisionChoice("fp32", "torch sees no CUDA device")
    assert resolve_precision("auto", torch.device("cuda"), "onnxruntime") == "fp32"


def test_onnxruntime_and_other_devices_take_fp32(monkeypatch):
    _cpu_with(monkeypatch, "amx_bf16")
    assert auto_choice("cpu", "onnxruntime") == PrecisionChoice(
        "fp32", "onnxruntime runs fp32 only"
    )
    assert auto_choice("mps").precision == "fp32"


def test_asked_precisions_stand_and_unknown_ones_are_refused(monkeypatch):
    _cpu_with(monkeypatch)
    for name in ("fp32", "fp16", "bf16"):
        assert resolve_precision(name, torch.device("cpu")) == name
    with pytest.raises(ValueError, match="--precision must be one of auto, fp32, fp16, bf16"):
        resolve_precision("fp8", torch.device("cpu"))
    assert PRECISIONS == ("auto", "fp32", "fp16", "bf16")


def test_the_choice_is_logged_and_kept_for_the_run_record(monkeypatch, caplog):
    _cpu_with(monkeypatch, "avx512_bf16")
    caplog.set_level(logging.INFO, "rangeret.inference.runtime.precision")
    resolve_precision("auto", torch.device("cpu"))
    resolve_precision("fp32", torch.device("cpu"))
    assert caplog.messages == [
        "precision bf16 on cpu, picked by --precision auto: this CPU has AVX-512 bf16 "
        "(avx512_bf16)",
        "precision fp32 on cpu: asked for (fp32 is the default); auto would pick bf16 here: "
        "this CPU has AVX-512 bf16 (avx512_bf16)",
    ]
    assert resolved_reason("bf16", "cpu") == precision_reason("bf16", "cpu")
    assert resolved_reason("fp16", "cuda:3") is None


def test_the_default_precision_is_fp32_and_training_keeps_auto():
    assert PRECISION.default == "fp32"
    assert "auto is bf16 where the CPU (AMX or AVX-512 bf16)" in PRECISION.help
    spec_help = option_help(
        next(f for f in dataclasses.fields(InferenceSpec) if f.name == "precision")
    )
    assert spec_help.endswith("(default: fp32)")
    assert InferenceSpec().precision == "fp32"
    assert TRAINING_PRECISION.default == "auto"
    assert TrainConfig(dataset="d", out="o").precision == "auto"


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
    bf16 = json.loads((tmp_path / "a" / "run.json").read_text())
    assert bf16["precision"] == "bf16"
    assert bf16["precision_reason"] == precision_reason("bf16", "cpu")
    assert bf16["runs"][0]["precision_reason"] == bf16["precision_reason"]
    assert main([*args, "--out", str(tmp_path / "b"), "--device", "cpu"]) == 0
    fp32 = json.loads((tmp_path / "b" / "run.json").read_text())
    assert fp32["precision"] == "fp32", "the default"
    assert fp32["precision_reason"] == precision_reason("fp32", "cpu")
    assert (
        main([*args, "--out", str(tmp_path / "d"), "--device", "cpu", "--precision", "auto"]) == 0
    )
    auto = json.loads((tmp_path / "d" / "run.json").read_text())
    assert auto["precision"] == auto_choice("cpu").precision
    assert auto["precision_reason"].startswith("auto's pick here: ")
    with pytest.raises(SystemExit):
        main([*args, "--out", str(tmp_path / "c"), "--precision", "fp64"])
    assert "invalid choice: 'fp64'" in capsys.readouterr().err
