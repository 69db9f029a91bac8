"""`rangeret bench`: the speed card's structure as JSON and as a table, the weights it times, and
its refusals. Timings are this machine's and are never compared with anything."""

from __future__ import annotations

import json

import pytest
import torch

from rangeret.cli.main import main
from rangeret.inference import knn_native
from rangeret.inference.runtime.cpu_features import FLAGS
from rangeret.inference.runtime.precision import auto_choice
from rangeret.inference.speed_inputs import DEFAULT_MODEL, bench_weights
from rangeret.models.weights import hub
from tests.support.workers import small_weights

SMALL = ["--height", "32", "--width", "256", "--device", "cpu"]
SPREAD = {"median_ms", "min_ms", "max_ms"}


def _card(capsys, *args: str) -> dict:
    assert main(["bench", "--json", "--rounds", "1", *args]) == 0
    return json.loads(capsys.readouterr().out)


def test_random_weights_give_a_card_with_fp32_agreeing_with_itself(capsys):
    card = _card(capsys, "--random", *SMALL)
    assert set(card) == {
        "machine",
        "auto_precision",
        "network",
        "scan",
        "rounds",
        "matmul_peak_gflops",
        "results",
        "seconds",
    }
    machine = card["machine"]
    assert machine["device"] == "cpu" and machine["gpu"] is None
    assert set(machine["cpu"]["flags"]) == set(FLAGS)
    assert machine["cpu"]["torch_threads"] == torch.get_num_threads()
    isa = knn_native.ISA_NAMES[knn_native.best_isa()]
    assert machine["knn_vote"].startswith(f"the compiled vote, {isa} (")
    auto = auto_choice("cpu")
    assert card["auto_precision"] == {"precision": auto.precision, "reason": auto.reason}
    network = card["network"]
    assert network["model"] == "rangeret-cir" and network["weights"] == "random"
    assert (network["height"], network["width"], network["profile"]) == (32, 256, "semantickitti")
    assert network["note"] == "--random" and network["gflop"] > 0
    assert card["scan"]["source"] == "simulated" and card["scan"]["points"] > 1000
    assert card["rounds"] == 1
    configs = [(r["backend"], r["precision"]) for r in card["results"]]
    expected = [("torch", "fp32")] + ([("torch", "bf16")] if auto.precision == "bf16" else [])
    assert configs == expected
    assert set(card["matmul_peak_gflops"]) == {p for _, p in expected}
    fp32 = card["results"][0]
    assert fp32["agreement_with_fp32"] == 1.0
    for result in card["results"]:
        for stage in ("forward", "projection", "knn", "scan"):
            spread = result[stage]
            assert set(spread) == SPREAD
            assert spread["min_ms"] <= spread["median_ms"] <= spread["max_ms"]
        assert result["scans_per_second"] > 0 and 0 <= result["agreement_with_fp32"] <= 1
        assert result["network_gflops_per_second"] > 0 and result["peak_fraction"] > 0


def test_a_checkpoint_on_the_real_scan_prints_a_table(tmp_path, capsys, real_scan_path):
    weights = small_weights(tmp_path)
    args = ["bench", "--rounds", "2", "--checkpoint", str(weights), "--scan", str(real_scan_path)]
    assert main([*args, *SMALL, "--precisions", "bf16"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("cpu ") and "torch threads" in lines[0]
    assert lines[1].removeprefix("flags").strip().split(", ")[:2] in (
        [f"AMX bf16 {amx}", f"AVX-512 bf16 {avx}"] for amx in ("yes", "no") for avx in ("yes", "no")
    )
    assert any(line.startswith("auto ") for line in lines)
    assert any(line.startswith("knn ") and "the compiled vote" in line for line in lines)
    assert any(line.startswith("weights ") and str(weights) in line for line in lines)
    assert any(line.startswith("scan ") and "123,389 points" in line for line in lines)
    header = next(i for i, line in enumerate(lines) if line.startswith("backend "))
    assert lines[header].split()[:2] == ["backend", "precision"]
    rows = [line.split()[:2] for line in lines[header + 1 :]]
    assert rows == [["torch", "fp32"], ["torch", "bf16"]]
    assert lines[header + 1].split()[-2] == "100.00%"


def test_the_default_model_not_downloaded_is_timed_with_random_weights(monkeypatch):
    monkeypatch.setattr(hub, "cached_weights", lambda model: None)
    bench = bench_weights(height=32, width=256)
    assert bench.model == "rangeret-cir" and bench.source == "random"
    assert bench.note == (
        f"{DEFAULT_MODEL} is not downloaded; rangeret weights download {DEFAULT_MODEL} to time it"
    )
    assert bench.weights.network.config.layers == 8, "the published network's blocks"
    assert bench.weights.profile.projection.height == 32
    thesis = bench_weights(model="rangeret-thesis", height=32, width=256)
    assert thesis.model == "rangeret-thesis" and thesis.note == "no checkpoint given"


def test_a_missing_checkpoint_is_one_line(tmp_path, capsys):
    missing = tmp_path / "nope.pt"
    assert main(["bench", "--checkpoint", str(missing), *SMALL]) == 1
    err = capsys.readouterr().err
    assert err.strip().splitlines() == [
        f"rangeret bench: error: --checkpoint {missing}: no such file, nor a published model's name"
    ]
    with pytest.raises(SystemExit):
        main(["bench", "--rounds", "0"])
    assert "must be at least 1, got 0" in capsys.readouterr().err


@pytest.mark.slow
def test_onnxruntime_is_timed_at_fp32_beside_torch(tmp_path, monkeypatch, capsys):
    pytest.importorskip("onnxruntime")
    monkeypatch.setenv("RANGERET_CACHE", str(tmp_path / "cache"))
    card = _card(capsys, "--random", *SMALL, "--backends", "torch", "onnxruntime")
    configs = [(r["backend"], r["precision"]) for r in card["results"]]
    assert configs[0] == ("torch", "fp32") and configs[-1] == ("onnxruntime", "fp32")
    assert card["results"][-1]["agreement_with_fp32"] > 0.99
    assert card["machine"]["onnxruntime"]
