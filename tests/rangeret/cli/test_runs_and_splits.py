"""Runs into one predictions tree (`run.json` keeps each; other weights need --overwrite) and
--allow-partial on every command that takes --split."""

from __future__ import annotations

import hashlib
import json
import logging
import shutil

import pytest
import torch

from rangeret.cli.main import main
from rangeret.dataset.layout import KITTI_LAYOUT, labels_dir, predictions_dir
from tests.support.trees import make_tree
from tests.support.workers import build_tree, small_weights, tree_bytes

NET = ["--height", "32", "--width", "256", "--device", "cpu"]


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    """Two checkpoints of the same network: the small weights and a perturbed copy."""
    folder = tmp_path_factory.mktemp("weights")
    first = small_weights(folder)
    state = torch.load(first, weights_only=True)
    name = next(k for k, v in state.items() if v.is_floating_point() and v.ndim > 1)
    state[name] = state[name] + 0.5
    second = folder / "other.pt"
    torch.save(state, second)
    return first, second


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Two labelled scans in 08 and one unlabelled in 11: of the test split, only 11."""
    return build_tree(tmp_path_factory.mktemp("tree") / "data", labelled=2, unlabelled=1)


def _sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _predict(data, out, weights, *extra):
    base = ["predict", "-q", "--dataset", str(data), "--out", str(out)]
    return main([*base, "--checkpoint", str(weights), *NET, *extra])


def test_two_runs_into_one_tree_are_both_recorded(data, weights, tmp_path, capsys):
    out = tmp_path / "pred"
    assert _predict(data, out, weights[0], "--sequences", "08") == 0
    assert _predict(data, out, weights[0], "--sequences", "11") == 0
    record = json.loads((out / "run.json").read_text())
    assert record["sequences"] == ["11"] and record["runner"] == "rangeret predict"
    assert [r["sequences"] for r in record["runs"]] == [["08"], ["11"]]
    assert record["runs"][0]["started"] <= record["runs"][1]["started"]
    assert {r["checkpoint_sha256"] for r in record["runs"]} == {_sha(weights[0])}
    assert len(tree_bytes(out)) == 3
    capsys.readouterr()


def test_other_weights_are_refused_unless_overwrite(data, weights, tmp_path, capsys):
    out = tmp_path / "pred"
    assert _predict(data, out, weights[0], "--sequences", "08") == 0
    before, record = tree_bytes(out), (out / "run.json").read_bytes()
    capsys.readouterr()
    assert _predict(data, out, weights[1], "--sequences", "08", "11") == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(out) in err and "--overwrite" in err
    assert _sha(weights[0])[:12] in err and _sha(weights[1])[:12] in err
    assert tree_bytes(out) == before and (out / "run.json").read_bytes() == record

    assert _predict(data, out, weights[1], "--sequences", "08", "--overwrite") == 0
    assert "2 written, 0 already done" in capsys.readouterr().out
    assert tree_bytes(out) != before, "every chosen scan was predicted again"
    runs = json.loads((out / "run.json").read_text())["runs"]
    assert [r["checkpoint_sha256"] for r in runs] == [_sha(weights[0]), _sha(weights[1])]
    assert [r["overwrite"] for r in runs] == [False, True]
    assert _predict(data, out, weights[0], "--sequences", "11") == 1, "the tree holds both now"
    capsys.readouterr()


def test_files_folders_keep_their_runs_and_refuse_other_weights(data, weights, tmp_path, capsys):
    inputs = tmp_path / "in"
    inputs.mkdir()
    scans = sorted(data.rglob("*.bin"))
    shutil.copy(scans[0], inputs / "a.bin")
    out = tmp_path / "out"
    args = ["predict", "-q", "--files", str(inputs / "a.bin"), "--out", str(out), *NET]
    assert main([*args, "--checkpoint", str(weights[0])]) == 0
    labels = (out / "a.label").read_bytes()
    capsys.readouterr()
    assert main([*args, "--checkpoint", str(weights[1])]) == 1
    err = capsys.readouterr().err
    assert _sha(weights[0])[:12] in err and _sha(weights[1])[:12] in err
    assert (out / "a.label").read_bytes() == labels
    assert main([*args, "--checkpoint", str(weights[1]), "--overwrite"]) == 0
    record = json.loads((out / "run.json").read_text())
    assert [r["files"] for r in record["runs"]] == [[str(inputs / "a.bin")]] * 2
    assert record["runs"][0]["started"] <= record["runs"][1]["started"]
    assert main([*args, "--checkpoint", str(weights[1]), "--allow-partial"]) == 1
    assert "--allow-partial are for --dataset" in capsys.readouterr().err


def test_predict_a_partial_split_only_with_allow_partial(data, weights, tmp_path, capsys, caplog):
    out = tmp_path / "pred"
    assert _predict(data, out, weights[0], "--split", "test") == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--allow-partial" in err
    assert (
        f"the test split's sequences 12, 13, 14, 15, 16, 17, 18, 19, 20, 21 are not in {data}"
        in err
    )
    assert not out.exists()
    with caplog.at_level(logging.WARNING, logger="rangeret"):
        assert _predict(data, out, weights[0], "--split", "test", "--allow-partial") == 0
    assert (
        f"--allow-partial: the test split's sequences 12, 13, 14, 15, 16, 17, 18, 19, 20, 21 are not in {data}; predicting 11"
        in caplog.text
    )
    assert sorted(tree_bytes(out)) == ["sequences/11/predictions/000002.label"]
    assert json.loads((out / "run.json").read_text())["sequences"] == ["11"]
    assert _predict(data, out, weights[0], "--sequences", "11", "12", "--allow-partial") == 1
    assert "sequence 12 is missing" in capsys.readouterr().err, "--sequences stay strict"
    assert _predict(data, out, weights[0], "--split", "train", "--allow-partial") == 1
    assert (
        "none of the train split's sequences (00, 01, 02, 03, 04, 05, 06, 07, 09, 10)"
        in capsys.readouterr().err
    )


@pytest.fixture
def train_tree(tmp_path):
    """Sequences 00 and 01 of the train split, labelled, and predictions equal to the labels."""
    root = tmp_path / "data"
    make_tree(root, {"00": [50, 60], "01": [40]})
    pred = tmp_path / "pred"
    for seq in ("00", "01"):
        shutil.copytree(labels_dir(root, seq, layout=KITTI_LAYOUT), predictions_dir(pred, seq))
    return root, pred


def test_evaluate_a_partial_split_only_with_allow_partial(train_tree, tmp_path, capsys, caplog):
    root, pred = train_tree
    base = [
        "evaluate",
        "-q",
        "--dataset",
        str(root),
        "--predictions",
        str(pred),
        "--split",
        "train",
    ]
    assert main(base) == 1
    err = capsys.readouterr().err
    assert "the train split's sequences 02, 03, 04, 05, 06, 07, 09, 10 are not in" in err
    assert "--allow-partial" in err
    report = tmp_path / "report.json"
    with caplog.at_level(logging.WARNING, logger="rangeret"):
        assert main([*base, "--allow-partial", "--json", str(report)]) == 0
    assert "; evaluating 00, 01" in caplog.text
    result = json.loads(report.read_text())
    assert result["sequences"] == ["00", "01"] and result["miou"] > 0.99
    capsys.readouterr()


def test_profile_stats_of_a_partial_split_only_with_allow_partial(train_tree, capsys, caplog):
    root, _ = train_tree
    base = ["profile", "stats", "--dataset", str(root), "--profile", "semantickitti"]
    assert main([*base, "--split", "train"]) == 1
    assert "--allow-partial" in capsys.readouterr().err
    with caplog.at_level(logging.WARNING, logger="rangeret"):
        assert main([*base, "--split", "train", "--allow-partial", "-q"]) == 0
    assert "; measuring 00, 01" in caplog.text
    assert "3 scans" in capsys.readouterr().out
