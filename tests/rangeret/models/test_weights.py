"""Published models by name, against a fake model hub on loopback.

A small HTTP server speaks the hub's download protocol (a HEAD with the commit and ETag, then the
bytes) for a published-format state_dict, and `HF_ENDPOINT` points the `rangeret` command at it;
`RANGERET_REGISTRY` adds test entries in the registry's own form. Covered: a name resolves to its
file, profile and resolution and labels like the file itself; a cached file needs no network; an
offline or unreachable hub, a truncated download and a SHA-256 mismatch each end in one sentence
and leave no file to be used; the built-in registry holds the release's facts.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest
import yaml

from rangeret.dataset.layout import KITTI_LAYOUT, prediction_path, velodyne_dir
from rangeret.dataset.profiles import load_profile
from rangeret.io.scans import KITTI_RECORD, read_labels, read_scan, write_scan
from rangeret.models.weights.registry import load_registry, profile_for_published
from tests.support.open_audit import Audit
from tests.support.paths import REPO, data_path
from tests.support.workers import small_weights

REPO_ID = "test-org/tiny-rangeret"
COMMIT = "0123456789abcdef0123456789abcdef01234567"
NET = ["--device", "cpu", "-q"]


class FakeHub(ThreadingHTTPServer):
    """Serves `files` under /REPO/resolve/REVISION/NAME as the hub does; `truncate` names files
    whose body stops half-way (the connection then closes)."""

    def __init__(self, files: dict[str, bytes]) -> None:
        super().__init__(("127.0.0.1", 0), _HubHandler)
        self.files = files
        self.truncate: set[str] = set()
        self.requests: list[str] = []

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.server_address[1]}"


class _HubHandler(BaseHTTPRequestHandler):
    server: FakeHub

    def log_message(self, *args) -> None:  # quiet
        pass

    def _file(self) -> tuple[str, bytes] | None:
        prefix = f"/{REPO_ID}/resolve/main/"
        if not self.path.startswith(prefix):
            return None
        name = self.path[len(prefix) :]
        data = self.server.files.get(name)
        return None if data is None else (name, data)

    def _head(self, data: bytes) -> None:
        self.send_response(200)
        self.send_header("X-Repo-Commit", COMMIT)
        self.send_header("ETag", f'"{hashlib.sha256(data).hexdigest()}"')
        self.send_header("Content-Length", str(len(data)))
        self.send_header("Connection", "close")
        self.end_headers()

    def do_HEAD(self) -> None:
        self.server.requests.append(f"HEAD {self.path}")
        found = self._file()
        if found is None:
            self.send_error(404)
            return
        self._head(found[1])

    def do_GET(self) -> None:
        self.server.requests.append(f"GET {self.path}")
        found = self._file()
        if found is None:
            self.send_error(404)
            return
        name, data = found
        self._head(data)
        self.wfile.write(data[: len(data) // 2] if name in self.server.truncate else data)
        self.wfile.flush()
        self.close_connection = True


@pytest.fixture(scope="module")
def weights(tmp_path_factory) -> dict:
    """The small published-format weights, their hash, and a one-scan dataset of the real scan."""
    base = tmp_path_factory.mktemp("weights")
    path = small_weights(base)
    data = base / "data"
    write_scan(
        velodyne_dir(data, "00", layout=KITTI_LAYOUT) / "000000.bin",
        read_scan(data_path("semantickitti-scan", "000000.bin"))[::4],
        record=KITTI_RECORD,
    )
    return {
        "path": path,
        "bytes": path.read_bytes(),
        "sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
        "data": data,
        "base": base,
    }


@pytest.fixture
def hub(weights) -> Iterator[FakeHub]:
    server = FakeHub(
        {"tiny.pt": weights["bytes"], "cut.pt": weights["bytes"], "other.pt": b"not the weights"}
    )
    server.truncate.add("cut.pt")
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield server
    server.shutdown()
    server.server_close()


def _entry(file: str, sha256: str | None, profile: str = "semantickitti") -> dict:
    return {
        "repo": REPO_ID,
        "file": file,
        "revision": "main",
        "model": "rangeret-cir",
        "blocks": 2,
        "height": 32,
        "width": 256,
        "profile": profile,
        "dataset": "SemanticKITTI",
        "miou": {"valid": 1.0, "test": None},
        "license": "not stated",
        "sha256": sha256,
        "size": None,
    }


@pytest.fixture
def env(tmp_path, weights, hub) -> dict[str, str]:
    """The `rangeret` command's environment: the fake hub, a fresh hub cache, test entries."""
    registry = tmp_path / "models.yaml"
    registry.write_text(
        yaml.safe_dump(
            {
                "tiny-kitti": _entry("tiny.pt", weights["sha256"]),
                "tiny-unpinned": _entry("tiny.pt", None),
                "tiny-cut": _entry("cut.pt", None),
                "tiny-wrong": _entry("other.pt", "0" * 64),
                "tiny-absent": _entry("absent.pt", None),
            }
        )
    )
    values = {k: v for k, v in os.environ.items() if not k.startswith(("HF_", "RANGERET_"))}
    values.update(
        HF_ENDPOINT=hub.url,
        HF_HOME=str(tmp_path / "hf"),
        HF_HUB_DISABLE_TELEMETRY="1",
        RANGERET_REGISTRY=str(registry),
    )
    return values


def rangeret(env: dict[str, str], *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "rangeret.cli.main", *args],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


def _one_sentence_error(run: subprocess.CompletedProcess) -> str:
    assert run.returncode == 1, run.stderr
    assert "Traceback" not in run.stderr
    errors = [line for line in run.stderr.splitlines() if ": error: " in line]
    assert len(errors) == 1, run.stderr
    return errors[0]


def _cached(env: dict[str, str]) -> list[Path]:
    return [p for p in Path(env["HF_HOME"]).rglob("*.pt") if p.is_file()]


def _predict(env: dict[str, str], weights: dict, out: Path, checkpoint: str, *extra: str):
    args = ["predict", "--dataset", str(weights["data"]), "--sequences", "00", "--out", str(out)]
    return rangeret(env, *args, "--checkpoint", checkpoint, *NET, *extra)


def test_a_name_resolves_to_its_file_profile_and_resolution(env, weights, hub, tmp_path):
    by_name = _predict(env, weights, tmp_path / "by-name", "tiny-kitti")
    assert by_name.returncode == 0, by_name.stderr
    assert weights["sha256"] in by_name.stderr  # printed
    by_file = _predict(
        env, weights, tmp_path / "by-file", str(weights["path"]), "--height", "32", "--width", "256"
    )
    assert by_file.returncode == 0, by_file.stderr
    labels = read_labels(prediction_path(tmp_path / "by-name", "00", "000000"))
    assert np.array_equal(
        labels, read_labels(prediction_path(tmp_path / "by-file", "00", "000000"))
    )
    run = json.loads((tmp_path / "by-name" / "run.json").read_text())
    assert json.dumps(run).count(weights["sha256"]) >= 1
    assert any(r.startswith("GET") for r in hub.requests)

    listed = rangeret(env, "weights", "list")
    assert listed.returncode == 0, listed.stderr
    row = next(line for line in listed.stdout.splitlines() if line.startswith("tiny-kitti "))
    assert " yes " in row and "MiB" in row and "val 1.0" in row
    assert row.endswith(weights["sha256"][:12])
    unpinned = next(line for line in listed.stdout.splitlines() if line.startswith("tiny-absent "))
    assert unpinned.endswith("not pinned  not pinned") and "unknown" not in listed.stdout


def test_predict_reads_its_checkpoint_once_by_name_or_by_path(env, weights, hub, tmp_path):
    """Downloaded, from the cache, or a path: one read of the file per run, its pin checked on
    the bytes that are loaded."""
    audit = Audit(tmp_path / "audit.log", ("tiny.pt", weights["path"].name))
    audited = audit.env(env)
    small = ("--height", "32", "--width", "256")
    runs = [
        _predict(audited, weights, tmp_path / "downloaded", "tiny-kitti"),
        _predict(audited, weights, tmp_path / "cached", "tiny-kitti"),
        _predict(audited, weights, tmp_path / "path", str(weights["path"]), *small),
    ]
    for run in runs:
        assert run.returncode == 0, run.stderr
    reads = audit.reads()
    assert len(reads) == 3 and set(reads.values()) == {1}, audit.lines()


def test_predict_refuses_a_file_that_is_not_the_pinned_one(env, weights, tmp_path):
    error = _one_sentence_error(_predict(env, weights, tmp_path / "out", "tiny-wrong"))
    assert "SHA-256" in error and "0" * 64 in error
    assert not _cached(env) and not (tmp_path / "out").exists()


def test_a_cached_file_needs_no_network(env, weights, hub, tmp_path):
    assert rangeret(env, "weights", "download", "tiny-kitti").returncode == 0
    hub.shutdown()
    hub.server_close()
    for values in ({**env, "HF_HUB_OFFLINE": "1"}, {**env, "HF_ENDPOINT": "http://127.0.0.1:9"}):
        run = _predict(values, weights, tmp_path / values["HF_ENDPOINT"][-1], "tiny-kitti")
        assert run.returncode == 0, run.stderr


def test_an_offline_or_unreachable_hub_is_one_sentence(env, weights, tmp_path):
    for values in ({**env, "HF_HUB_OFFLINE": "1"}, {**env, "HF_ENDPOINT": "http://127.0.0.1:9"}):
        error = _one_sentence_error(_predict(values, weights, tmp_path / "out", "tiny-kitti"))
        url = f"{values['HF_ENDPOINT']}/{REPO_ID}/resolve/main/tiny.pt"
        assert url in error and "--checkpoint /path/to/tiny.pt" in error
    error = _one_sentence_error(rangeret(env, "weights", "download", "tiny-absent"))
    assert "HTTP 404" in error
    assert not _cached(env)


def test_a_truncated_download_is_refused_and_never_used(env, weights, hub):
    error = _one_sentence_error(rangeret(env, "weights", "download", "tiny-cut"))
    assert "cut.pt" in error
    assert not _cached(env), "a partial file was left where it would be used"
    hub.truncate.clear()
    done = rangeret(env, "weights", "download", "tiny-cut")
    assert done.returncode == 0, done.stderr
    assert [p.read_bytes() for p in _cached(env)] == [weights["bytes"]]


def test_a_sha256_mismatch_is_refused_and_the_file_removed(env):
    error = _one_sentence_error(rangeret(env, "weights", "download", "tiny-wrong"))
    assert "SHA-256" in error and "0" * 64 in error
    assert not _cached(env)


def test_download_to_a_folder(env, weights, tmp_path):
    run = rangeret(env, "weights", "download", "tiny-unpinned", "--to", str(tmp_path / "models"))
    assert run.returncode == 0, run.stderr
    assert (tmp_path / "models" / "tiny.pt").read_bytes() == weights["bytes"]
    # An unpinned file's hash and size are logged, once, for the user to pin.
    said = " ".join(run.stderr.split())
    assert said.count("tiny-unpinned is not pinned") == 1, run.stderr
    assert f"sha256 {weights['sha256']} and {len(weights['bytes'])} bytes" in said
    assert not _cached(env)


def test_a_name_brings_its_profile_and_refuses_another():
    registry = load_registry()
    poss = registry["rangeret-poss-528"]
    assert profile_for_published(poss, None).name == "semantic-poss"
    assert profile_for_published(poss, load_profile("semantic-poss")).name == "semantic-poss"
    with pytest.raises(ValueError, match="semantic-poss profile and cannot run with the"):
        profile_for_published(poss, load_profile("semantickitti"))


def test_the_builtin_registry_holds_the_release_facts():
    registry = load_registry()
    assert set(registry) >= {"rangeret-kitti-657", "rangeret-panda-600", "rangeret-poss-528"}
    facts = {
        "rangeret-kitti-657": ("semantickitti", 64, 1024, 65.7, 64.5),
        "rangeret-panda-600": ("pandaset", 64, 1024, 66.7, 60.0),
        "rangeret-poss-528": ("semantic-poss", 40, 2048, None, 52.8),
    }
    for name, (profile, height, width, valid, test) in facts.items():
        model = registry[name]
        assert (model.repo, model.file) == ("Simom0/RangeRet", f"{name}.pt")
        assert (model.model, model.blocks) == ("rangeret-cir", 8)
        assert (model.profile, model.height, model.width) == (profile, height, width)
        assert (model.miou_valid, model.miou_test) == (valid, test)
        assert model.license == "not stated"
        assert model.sha256 is None and model.size is None  # unknown, so left empty
        assert load_profile(profile).projection.height == height
