"""A nuScenes tree's tables are data: `rangeret predict --profile nuscenes` (the real command line)
refuses every hostile shape (tokens that are paths, files outside the tree, a cycle with a huge
claimed count, huge, dense or deep tables, a FIFO) in one sentence naming the table, record and
field, exits 1 in bounded time and writes nothing outside --out; the bounded reader on its own."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from rangeret.dataset.json_tables import LIMITS_VARIABLE, TableError, read_table, table_limits
from tests.support.nuscenes import network, write_tree
from tests.support.paths import REPO
from tests.support.table_probes import ESCAPED, PROBES, VERSION, tree_files, write_files

TIMEOUT = 60


@pytest.fixture(scope="module")
def tree(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tree(tmp_path_factory.mktemp("probe-tree") / "nu", {"scene-0103": 2})


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("probe-weights") / "nu.pt"
    torch.save(network(0).state_dict(), path)
    return path


def _predict(root: Path, out: Path, checkpoint: Path) -> subprocess.CompletedProcess[str]:
    command = [sys.executable, "-m", "rangeret.cli.main", "predict", "-q", "--profile"]
    command += ["nuscenes", "--dataset", str(root), "--sequences", "scene-0103"]
    command += ["--checkpoint", str(checkpoint), "--height", "32", "--width", "256"]
    command += ["--device", "cpu", "--out", str(out)]
    env = {k: v for k, v in os.environ.items() if k != LIMITS_VARIABLE}
    return subprocess.run(
        command, capture_output=True, text=True, timeout=TIMEOUT, cwd=REPO, env=env
    )


@pytest.mark.slow
@pytest.mark.parametrize("probe", list(PROBES))
def test_predict_refuses_each_hostile_table(probe, tree, checkpoint, tmp_path):
    rewrite, expected = PROBES[probe]
    root = write_files(tmp_path / "work" / "tree", rewrite(tree_files(tree)))
    out = tmp_path / "work" / "out"
    start = time.monotonic()
    done = _predict(root, out, checkpoint)
    assert time.monotonic() - start < TIMEOUT
    assert done.returncode == 1, done.stderr
    errors = [line for line in done.stderr.splitlines() if "error:" in line]
    assert len(errors) == 1 and expected in errors[0], done.stderr
    assert "Traceback" not in done.stderr
    assert (
        not list(tmp_path.rglob(f"*{ESCAPED}")) and not Path("/tmp/escaped_lidarseg.bin").exists()
    )
    assert not list(out.rglob("*_lidarseg.bin"))


@pytest.mark.slow
def test_a_fifo_table_is_refused_without_waiting(tree, checkpoint, tmp_path):
    root = write_files(tmp_path / "tree", tree_files(tree))
    (root / VERSION / "sample.json").unlink()
    os.mkfifo(root / VERSION / "sample.json")
    done = _predict(root, tmp_path / "out", checkpoint)
    assert done.returncode == 1, done.stderr
    assert "sample.json is a FIFO (named pipe), not a file" in done.stderr


def test_a_table_that_is_a_folder_or_device_is_refused(tmp_path):
    (tmp_path / "scene.json").mkdir()
    with pytest.raises(TableError, match=r"scene.json is a folder, not a file"):
        read_table(tmp_path / "scene.json", "scene")
    with pytest.raises(TableError, match=r"/dev/zero is a character device, not a file"):
        read_table(Path("/dev/zero"), "scene")


def test_the_limits_are_checked_before_reading_and_settable(tmp_path, monkeypatch):
    table = tmp_path / "category.json"
    record = {"token": "0" * 32, "name": "noise", "description": "x" * 200, "index": 0}
    table.write_text(json.dumps([record] * 5000))  # about 1.4 MB
    with pytest.raises(TableError, match=rf"more than the 1,048,576 .*{LIMITS_VARIABLE}"):
        read_table(table, "category")
    monkeypatch.setenv(LIMITS_VARIABLE, "category=2MiB, sample=1GB")
    assert table_limits()["category"] == 2 << 20 and table_limits()["sample"] == 10**9
    assert len(read_table(table, "category")) == 5000
    monkeypatch.setenv(LIMITS_VARIABLE, "category=lots")
    with pytest.raises(TableError, match="write table=SIZE pairs"):
        table_limits()


def test_dense_tables_are_refused_before_parsing(tmp_path):
    table = tmp_path / "sample.json"
    for dense in (b"[" + b"{}," * 1000 + b"{}]", b"[" + b"1," * 1000 + b"1]"):
        table.write_bytes(dense)
        with pytest.raises(TableError, match=r"JSON values in .* bytes, more than one per 6"):
            read_table(table, "sample")


def test_records_are_kept_as_selected_and_faults_named(tmp_path):
    table = tmp_path / "sample.json"
    records = [{"token": f"{i:032x}", "next": ""} for i in range(10)]
    table.write_text(json.dumps(records, indent=1))
    kept = read_table(table, "sample", lambda i, r: {"i": i} if i % 3 == 0 else None)
    assert kept == [{"i": 0}, {"i": 3}, {"i": 6}, {"i": 9}]
    assert read_table(table, "sample") == records
    faults = {
        b"[]": None,
        b' [ {"token": "a"} ] \n': None,
        b'[{"token": "a"},]': "a comma before its closing",
        b'[{"token": "a"}] x': "data after its closing",
        b'{"token": "a"}': "does not start with '['",
        b'[{"token": "a"} {"token": "b"}]': "expected ',' or ']' after record 0",
        b'[{"token": "a"}, 7]': "record 1 is not an object",
        b"[\xff]": "is not UTF-8 text",
    }
    for data, problem in faults.items():
        table.write_bytes(data)
        if problem is None:
            assert isinstance(read_table(table, "sample"), list)
            continue
        with pytest.raises(TableError, match=re.escape(problem)):
            read_table(table, "sample")


def test_a_token_of_the_simulated_tree_matches_the_format(tree):
    records = json.loads((tree / VERSION / "sample_data.json").read_text())
    assert all(len(r["token"]) == 32 and int(r["token"], 16) >= 0 for r in records)
