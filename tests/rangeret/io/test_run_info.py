"""`run.json`: every run into a tree kept, oldest first; other weights refused unless overwriting."""

from __future__ import annotations

import json

import pytest

from rangeret.exceptions import InputError
from rangeret.io.run_info import (
    RUN_INFO,
    RunInfoError,
    WeightsMismatchError,
    check_weights,
    read_run_info,
    write_run_info,
)

SHA_A = "a" * 64
SHA_B = "b" * 64


def _network(sha: str) -> dict:
    return {
        "model": "rangeret-cir",
        "checkpoint": f"/w/{sha[0]}.pt",
        "checkpoint_sha256": sha,
        "demo_weights": False,
        "profile": "semantickitti",
        "precision": "fp32",
        "backend": "torch",
        "device": "cpu",
    }


def _write(out, sha, sequences, **options):
    return write_run_info(
        out,
        _network(sha),
        runner="rangeret predict",
        dataset="/data",
        sequences=sequences,
        batch_size=1,
        **options,
    )


def test_each_run_is_added_oldest_first_and_the_top_level_is_the_latest(tmp_path):
    _write(tmp_path, SHA_A, ["08"], started="2026-01-01T10:00:00+0000")
    _write(tmp_path, SHA_A, ["11", "12"], started="2026-01-02T10:00:00+0000")
    record = read_run_info(tmp_path)
    assert record["sequences"] == ["11", "12"] and record["started"].startswith("2026-01-02")
    assert record["checkpoint_sha256"] == SHA_A and record["runner"] == "rangeret predict"
    runs = record["runs"]
    assert [r["sequences"] for r in runs] == [["08"], ["11", "12"]]
    assert [r["started"][:10] for r in runs] == ["2026-01-01", "2026-01-02"]
    for key in ("checkpoint", "checkpoint_sha256", "demo_weights", "precision", "backend"):
        assert runs[0][key] == _network(SHA_A)[key]
    assert runs[0]["overwrite"] is False and "runs" not in runs[0]


def test_a_record_written_before_runs_were_listed_becomes_the_first_run(tmp_path):
    legacy = {**_network(SHA_A), "sequences": ["08"], "runner": "workers.predict_job"}
    legacy |= {"dataset": "/data", "batch_size": 2, "started": "2025-12-01T09:00:00+0000"}
    (tmp_path / RUN_INFO).write_text(json.dumps(legacy))
    _write(tmp_path, SHA_A, ["11"])
    runs = read_run_info(tmp_path)["runs"]
    assert len(runs) == 2
    assert runs[0] == legacy
    assert runs[1]["sequences"] == ["11"]


def test_other_weights_are_refused_naming_both_hashes_and_the_tree(tmp_path):
    _write(tmp_path, SHA_A, ["08"])
    before = (tmp_path / RUN_INFO).read_bytes()
    with pytest.raises(WeightsMismatchError) as caught:
        _write(tmp_path, SHA_B, ["11"])
    message = str(caught.value)
    assert str(tmp_path) in message and "aaaaaaaaaaaa" in message and "bbbbbbbbbbbb" in message
    assert "--overwrite" in message and isinstance(caught.value, InputError)
    assert (tmp_path / RUN_INFO).read_bytes() == before
    check_weights(tmp_path, SHA_A)  # the same weights again: a resumed or extended run

    _write(tmp_path, SHA_B, ["11"], overwrite=True)
    record = read_run_info(tmp_path)
    assert [r["checkpoint_sha256"] for r in record["runs"]] == [SHA_A, SHA_B]
    assert record["overwrite"] is True and record["runs"][1]["overwrite"] is True
    with pytest.raises(WeightsMismatchError, match="bbbbbbbbbbbb"):
        check_weights(tmp_path, SHA_A)  # the tree now holds both


def test_a_tree_without_a_record_takes_any_weights(tmp_path):
    assert check_weights(tmp_path / "new", SHA_B) == {}


def test_files_runs_list_the_files_they_labelled(tmp_path):
    inputs = [{"file": "/in/a.pcd", "points": 3}, {"file": "/in/b.ply", "points": 4}]
    write_run_info(
        tmp_path,
        _network(SHA_A),
        runner="rangeret predict --files",
        dataset=None,
        sequences=[],
        batch_size=1,
        inputs=inputs,
    )
    record = read_run_info(tmp_path)
    assert record["inputs"] == inputs and record["runs"][0]["files"] == ["/in/a.pcd", "/in/b.ply"]


def test_a_record_whose_runs_are_not_a_list_is_one_error(tmp_path):
    (tmp_path / RUN_INFO).write_text(json.dumps({**_network(SHA_A), "runs": "x"}))
    with pytest.raises(RunInfoError, match="`runs` is not a list"):
        _write(tmp_path, SHA_A, ["08"])


def test_a_record_nested_100000_deep_is_one_error(tmp_path):
    (tmp_path / RUN_INFO).write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(RunInfoError) as exc:
        check_weights(tmp_path, SHA_A)
    assert (
        str(exc.value)
        == f"{tmp_path / RUN_INFO} is not a readable run record (it nests too deeply)"
    )
