"""Checkpoints, exports and models-file entries that are not regular files (a folder, a FIFO,
`/dev/zero`) are refused by their kind in one sentence, at once, by the real command line and by a
real `rangeret serve` starting up; none of them hangs, fills memory or shows a traceback."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.support.gateway import LIMITS, NET
from tests.support.paths import REPO, data_path

TIMEOUT = 60
KINDS = {
    "folder": "is a folder, not a file",
    "fifo": "is a FIFO (named pipe), not a file",
    "device": "is a character device, not a file",
}


def _made(kind: str, folder: Path) -> Path:
    if kind == "device":
        return Path("/dev/zero")
    path = folder / f"weights-{kind}.pt"
    if kind == "folder":
        path.mkdir()
    else:
        os.mkfifo(path)
    return path


def _run(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, *args], capture_output=True, text=True, timeout=TIMEOUT, cwd=REPO, env=env
    )


@pytest.mark.slow
@pytest.mark.parametrize("kind", list(KINDS))
def test_commands_refuse_a_checkpoint_that_is_not_a_file(kind, tmp_path):
    path = _made(kind, tmp_path)
    scan = str(data_path("semantickitti-scan", "000000.bin"))
    commands = [
        ["predict", "-q", "--checkpoint", str(path), "--files", scan, "--out", str(tmp_path)],
        ["weights", "info", str(path)],
    ]
    for command in commands:
        done = _run("-m", "rangeret.cli.main", *command)
        assert done.returncode == 1, done.stderr
        assert f"{path} {KINDS[kind]}: a checkpoint must be a regular file" in done.stderr
        assert "Traceback" not in done.stderr


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["fifo", "device"])
def test_serve_refuses_a_models_file_entry_that_is_not_a_file(kind, tmp_path):
    models = tmp_path / "models.yaml"
    entry = {"checkpoint": str(_made(kind, tmp_path))}
    models.write_text(yaml.safe_dump({"default": "m", "models": {"m": entry}}))
    env = {k: v for k, v in os.environ.items() if not k.startswith("RANGERET_")}
    env |= LIMITS | {"RANGERET_STATE_DIR": str(tmp_path / "state")}
    done = _run("-m", "service", "--models", str(models), *NET, "--port", "0", env=env)
    assert done.returncode != 0
    assert KINDS[kind] in done.stderr and "Traceback" not in done.stderr, done.stderr


@pytest.mark.slow
def test_a_scan_that_is_a_fifo_is_that_scans_named_failure(tmp_path):
    from tests.support.workers import build_tree, small_weights

    data = build_tree(tmp_path / "data", labelled=2, unlabelled=0)
    fifo = data / "sequences" / "08" / "velodyne" / "000001.bin"
    fifo.unlink()
    os.mkfifo(fifo)
    out = tmp_path / "out"
    args = ["-m", "rangeret.cli.main", "predict", "--dataset", str(data), "--sequences", "08"]
    done = _run(*args, "--out", str(out), "--checkpoint", str(small_weights(tmp_path)), *NET)
    assert done.returncode == 1, done.stderr
    assert f"{fifo}: it is a FIFO (named pipe), not a scan file" in done.stderr + done.stdout
    assert (out / "sequences" / "08" / "predictions" / "000000.label").is_file()


def test_a_profile_that_is_a_fifo_is_one_sentence(tmp_path):
    os.mkfifo(tmp_path / "p.yaml")
    done = _run("-m", "rangeret.cli.main", "profile", "show", str(tmp_path / "p.yaml"))
    assert done.returncode == 1
    assert "p.yaml is a FIFO (named pipe), not a file" in done.stderr, done.stderr
