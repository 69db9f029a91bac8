"""One gateway, several models: `rangeret serve --models` against real uvicorn processes.

Two SemanticKITTI checkpoints of different weights and a PandaSet one: `?model=` gives each its
own `rangeret predict` labels byte for byte (in its profile's record and raw ids), no name gives
the default, an unknown name is a 404 naming the models, `/v1/models`, `/v1/model`,
`/v1/profile` and `/healthz` describe each model (with the precision it runs at and why, and
what `--precision auto` picks on this machine), a dataset or archive job with each model
gives that model's labels; with `--max-loaded 1` requests alternating
between two models stay right while one network is loaded at a time; and a models file beside
`--checkpoint`, or a wrong one, stops `rangeret serve` with one line.
"""

from __future__ import annotations

import io
import subprocess
import sys
import zipfile
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch
import yaml

from rangeret.cli.main import main as rangeret_main
from rangeret.dataset.layout import prediction_path
from rangeret.dataset.profiles import load_profile
from rangeret.inference.runtime.precision import auto_choice, precision_reason
from rangeret.models import build_model
from rangeret.sim import simulate_dataset
from tests.support.gateway import (
    NET,
    Gateway,
    assert_error,
    free_port,
    gateway_env,
    start_gateway,
    wait_job,
)
from tests.support.paths import REPO
from tests.support.workers import build_tree

OCTET = {"Content-Type": "application/octet-stream"}
KITTI_SCANS = [("08", "000000"), ("11", "000001")]


def _weights(path: Path, classes: int, seed: int) -> Path:
    """A published-format 1-block rangeret-cir at 32 x 256 with its own random weights."""
    torch.manual_seed(seed)
    torch.save(
        build_model("rangeret-cir", 32, 256, num_classes=classes, layers=1).state_dict(), path
    )
    return path


def _predict(data: Path, out: Path, weights: Path, sequences: list[str], *extra: str) -> Path:
    args = ["predict", "-q", "--dataset", str(data), "--sequences", *sequences, "--out", str(out)]
    assert rangeret_main([*args, "--checkpoint", str(weights), *NET, *extra]) == 0
    return out


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """Three checkpoints, a SemanticKITTI and a PandaSet tree, each model's reference labels and
    the models file naming them (`two` the default)."""
    base = tmp_path_factory.mktemp("models-gateway")
    roots = base / "roots"
    kitti = build_tree(roots / "kitti", labelled=1, unlabelled=1)
    panda_profile = load_profile("pandaset").with_overrides(height=32, width=256)
    simulate_dataset(roots / "panda", {"1": 1}, seed=5, profile=panda_profile)
    weights = {
        "one": _weights(base / "one.pt", 20, 0),
        "two": _weights(base / "two.pt", 20, 1),
        "panda": _weights(base / "panda.pt", 15, 2),
    }
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        refs = {
            name: _predict(kitti, base / f"ref-{name}", weights[name], ["08", "11"])
            for name in ("one", "two")
        }
        refs["panda"] = _predict(
            roots / "panda", base / "ref-panda", weights["panda"], ["1"], "--profile", "pandaset"
        )
    finally:
        torch.set_num_threads(threads)
    models = base / "models.yaml"
    models.write_text(
        yaml.safe_dump(
            {
                "default": "two",
                "models": {
                    "one": {"checkpoint": str(weights["one"])},
                    "two": {"checkpoint": str(weights["two"])},
                    "panda": {"checkpoint": str(weights["panda"]), "profile": "pandaset"},
                },
            },
            sort_keys=False,
        )
    )
    return {"base": base, "roots": roots, "kitti": kitti, "refs": refs, "models": models}


def _serve(setup: dict, name: str, *args: str) -> Gateway:
    env = gateway_env(setup["base"] / f"state-{name}", [setup["roots"]])
    log = setup["base"] / f"{name}.log"
    return start_gateway(None, env, log, "--models", str(setup["models"]), *args)


@pytest.fixture(scope="module")
def gateway(setup: dict) -> Iterator[Gateway]:
    gw = _serve(setup, "all")
    yield gw
    gw.stop()


def _kitti_scan(setup: dict, seq: str, name: str) -> bytes:
    return (setup["kitti"] / "sequences" / seq / "velodyne" / f"{name}.bin").read_bytes()


def _expected(setup: dict, model: str, seq: str, name: str) -> bytes:
    return prediction_path(setup["refs"][model], seq, name).read_bytes()


def test_each_model_labels_as_rangeret_predict_does_with_its_checkpoint(setup, gateway):
    with gateway.client() as client:
        for seq, name in KITTI_SCANS:
            body = _kitti_scan(setup, seq, name)
            answers = {
                model: client.post(
                    "/v1/scans", params={"model": model}, content=body, headers=OCTET
                )
                for model in ("one", "two")
            }
            default = client.post("/v1/scans", content=body, headers=OCTET)
            for model, answer in answers.items():
                assert answer.status_code == 200, answer.text
                assert answer.headers["x-rangeret-model"] == model
                assert answer.content == _expected(setup, model, seq, name), (model, seq)
            assert answers["one"].content != answers["two"].content
            assert default.headers["x-rangeret-model"] == "two"
            assert default.content == answers["two"].content
        panda = setup["roots"] / "panda" / "001" / "velodyne" / "000000.bin"
        as_json = client.post(
            "/v1/scans",
            params={"model": "panda", "format": "json"},
            content=panda.read_bytes(),
            headers=OCTET,
        )
        wrong_record = client.post(
            "/v1/scans", params={"model": "one"}, content=panda.read_bytes()[:40], headers=OCTET
        )
    assert as_json.status_code == 200, as_json.text
    body = as_json.json()
    assert body["model"] == "panda" and as_json.headers["x-rangeret-model"] == "panda"
    expected = prediction_path(setup["refs"]["panda"], "001", "000000").read_bytes()
    assert body["labels"] == list(memoryview(expected).cast("I"))
    assert set(body["class_counts"]) <= set(load_profile("pandaset").labels.class_names)
    # 40 bytes are two PandaSet records but not whole SemanticKITTI ones: read with `one`'s.
    assert "16 bytes per point" in assert_error(wrong_record, 400)


def test_an_unknown_model_is_a_404_naming_the_models(gateway):
    with gateway.client() as client:
        answers = [
            client.post("/v1/scans", params={"model": "poss"}, content=b"\0" * 16, headers=OCTET),
            client.get("/v1/model", params={"model": "poss"}),
            client.get("/v1/profile", params={"model": "poss"}),
        ]
    for answer in answers:
        detail = assert_error(answer, 404)
        assert "'poss'" in detail and "one, two, panda" in detail


def test_the_models_are_described_each_with_its_profile(gateway):
    with gateway.client() as client:
        listing = client.get("/v1/models").json()
        default = client.get("/v1/model").json()
        panda = client.get("/v1/model", params={"model": "panda"}).json()
        profile = client.get("/v1/profile", params={"model": "panda"}).json()
        health = client.get("/healthz").json()
    assert listing["default"] == "two"
    assert [m["id"] for m in listing["models"]] == ["one", "two", "panda"]
    assert all(m["loaded"] and m["name"] == "rangeret-cir" for m in listing["models"])
    shas = {m["id"]: m["checkpoint_sha256"] for m in listing["models"]}
    assert len(set(shas.values())) == 3
    assert default["id"] == "two" and default["checkpoint_sha256"] == shas["two"]
    assert panda["profile"] == "pandaset" and panda["checkpoint_sha256"] == shas["panda"]
    assert profile["profile"] == "pandaset" and profile["point_bytes"] == 20
    assert health["models"] == {"one": "semantickitti", "two": "semantickitti", "panda": "pandaset"}
    assert health["profile"] == "semantickitti"
    # fp32, the default, on this machine's CPU: the gateway says why, as this process works it out
    why = precision_reason("fp32", "cpu")
    for described in (*listing["models"], default, panda):
        assert (described["precision"], described["precision_reason"]) == ("fp32", why)
    assert (health["precision"], health["precision_reason"]) == ("fp32", why)
    assert [w["precision_reason"] for w in health["workers"]] == [why] * 3


def test_precision_auto_is_resolved_on_this_machine_and_said_with_why(setup):
    weights = setup["base"] / "one.pt"
    env = gateway_env(setup["base"] / "state-auto", [setup["roots"]])
    gw = start_gateway(weights, env, setup["base"] / "auto.log", "--precision", "auto")
    try:
        with gw.client() as client:
            model = client.get("/v1/model").json()
            health = client.get("/healthz").json()
            answer = client.post(
                "/v1/scans", content=_kitti_scan(setup, *KITTI_SCANS[0]), headers=OCTET
            )
    finally:
        gw.stop()
    picked = auto_choice("cpu")
    why = f"auto's pick here: {picked.reason}"
    assert (model["precision"], model["precision_reason"]) == (picked.precision, why)
    assert (health["precision"], health["precision_reason"]) == (picked.precision, why)
    assert [w["precision"] for w in health["workers"]] == [picked.precision]
    assert answer.status_code == 200, answer.text


def test_one_loaded_network_serves_two_models_in_turn(setup):
    gw = _serve(setup, "one-slot", "--max-loaded", "1")
    try:
        with gw.client() as client:
            assert _loaded(client) == ["two"]  # the default, loaded when checked at start
            for model in ("one", "two", "one", "two", "one"):
                for seq, name in KITTI_SCANS:
                    answer = client.post(
                        "/v1/scans",
                        params={"model": model},
                        content=_kitti_scan(setup, seq, name),
                        headers=OCTET,
                    )
                    assert answer.status_code == 200, answer.text
                    assert answer.content == _expected(setup, model, seq, name), (model, seq)
                assert _loaded(client) == [model]
                metrics = client.get("/metrics").text
                assert f'rangeret_model_loaded{{model="{model}"}} 1.0' in metrics
                other = "two" if model == "one" else "one"
                assert f'rangeret_model_loaded{{model="{other}"}} 0.0' in metrics
            labelled = 'rangeret_scans_labelled_total{model="one",source="request"} 6.0'
            assert labelled in metrics
    finally:
        gw.stop()


def _loaded(client) -> list[str]:
    return [m["id"] for m in client.get("/v1/models").json()["models"] if m["loaded"]]


def _serve_fails(setup: dict, *args: str) -> str:
    port = str(free_port())
    cmd = [sys.executable, "-m", "service", *NET, "--port", port, *args]
    env = gateway_env(setup["base"] / "state-refused", [setup["roots"]])
    run = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert run.returncode == 1, run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in run.stderr, run.stderr
    return lines[0]


def test_a_models_file_beside_a_checkpoint_or_a_wrong_one_is_one_line(setup, tmp_path):
    models = str(setup["models"])
    beside = _serve_fails(setup, "--models", models, "--checkpoint", "w.pt")
    assert "give --checkpoint in the models file" in beside
    wrong = tmp_path / "wrong.yaml"
    wrong.write_text("models: {one: {checkpoint: w.pt}, two: {checkpoint: v.pt}}\n")
    assert f"{wrong}: default: is missing; name one of one, two" in _serve_fails(
        setup, "--models", str(wrong)
    )
    missing = tmp_path / "missing.yaml"
    missing.write_text(f"default: a\nmodels: {{a: {{checkpoint: {tmp_path / 'absent.pt'}}}}}\n")
    assert "absent.pt" in _serve_fails(setup, "--models", str(missing))


def _served_labels(client, job_id: str) -> dict[str, bytes]:
    archive = client.get(f"/v1/jobs/{job_id}/predictions").content
    with zipfile.ZipFile(io.BytesIO(archive)) as zf:
        return {n: zf.read(n) for n in zf.namelist() if n.endswith(".label")}


def _reference(ref: Path) -> dict[str, bytes]:
    return {p.relative_to(ref).as_posix(): p.read_bytes() for p in ref.rglob("*.label")}


def test_a_job_with_each_model_gives_that_models_labels(setup, gateway):
    panda_scan = setup["roots"] / "panda" / "001" / "velodyne" / "000000.bin"
    upload = io.BytesIO()
    with zipfile.ZipFile(upload, "w") as zf:
        zf.writestr("sequences/001/velodyne/000000.bin", panda_scan.read_bytes())
    with gateway.client() as client:
        jobs = {
            model: client.post(
                "/v1/jobs", json={"dataset": "kitti", "sequences": ["08", "11"], "model": model}
            ).json()["id"]
            for model in ("one", "two")
        }
        default = client.post("/v1/jobs", json={"dataset": "kitti", "sequences": ["08", "11"]})
        panda = client.post(
            "/v1/jobs", json={"dataset": "panda", "sequences": ["1"], "model": "panda"}
        )
        uploaded = client.post(
            "/v1/jobs/uploads",
            params={"model": "panda"},
            files={"archive": ("panda.zip", upload.getvalue(), OCTET["Content-Type"])},
        )
        mismatch = client.post(
            "/v1/jobs",
            json={"dataset": "panda", "sequences": ["1"], "model": "one", "profile": "pandaset"},
        )
        unknown = client.post(
            "/v1/jobs", json={"dataset": "kitti", "sequences": ["08"], "model": "poss"}
        )
        unknown_upload = client.post(
            "/v1/jobs/uploads",
            params={"model": "poss"},
            files={"archive": ("panda.zip", upload.getvalue(), OCTET["Content-Type"])},
        )
        statuses = {
            name: wait_job(client, job_id)
            for name, job_id in {
                **jobs,
                "default": default.json()["id"],
                "panda": panda.json()["id"],
                "uploaded": uploaded.json()["id"],
            }.items()
        }
        served = {name: _served_labels(client, s["id"]) for name, s in statuses.items()}
    assert {name: s["state"] for name, s in statuses.items()} == dict.fromkeys(
        statuses, "succeeded"
    )
    assert {name: s["model"] for name, s in statuses.items()} == {
        "one": "one",
        "two": "two",
        "default": "two",
        "panda": "panda",
        "uploaded": "panda",
    }
    for model in ("one", "two"):
        assert served[model] == _reference(setup["refs"][model]) and len(served[model]) == 2
    assert served["default"] == served["two"] != served["one"]
    assert served["panda"] == _reference(setup["refs"]["panda"])
    assert served["uploaded"] == served["panda"]
    detail = assert_error(mismatch, 400)
    assert "'pandaset' profile" in detail and "model one" in detail and "'semantickitti'" in detail
    assert "'poss'" in assert_error(unknown, 404)
    assert "'poss'" in assert_error(unknown_upload, 404)


def test_a_checkpoint_changed_after_eviction_is_a_503_never_other_labels(setup, tmp_path):
    """`one` is checked at start, evicted, then its file is replaced by other weights, then
    truncated: loading it again is a 503 naming the model and both digests (logged once per
    reason), `/v1/model` keeps the start's SHA-256, and `two` still answers."""
    one = tmp_path / "one.pt"
    one.write_bytes((setup["base"] / "one.pt").read_bytes())
    models = tmp_path / "models.yaml"
    entries = {
        "one": {"checkpoint": str(one)},
        "two": {"checkpoint": str(setup["base"] / "two.pt")},
    }
    models.write_text(yaml.safe_dump({"default": "two", "models": entries}, sort_keys=False))
    env = gateway_env(tmp_path / "state", [setup["roots"]])
    gw = start_gateway(None, env, tmp_path / "gw.log", "--models", str(models), "--max-loaded", "1")
    scan = _kitti_scan(setup, *KITTI_SCANS[0])
    try:
        with gw.client() as client:
            started = client.get("/v1/model", params={"model": "one"}).json()["checkpoint_sha256"]

            def label(model: str):
                return client.post(
                    "/v1/scans", params={"model": model}, content=scan, headers=OCTET
                )

            assert label("one").content == _expected(setup, "one", *KITTI_SCANS[0])
            assert label("two").status_code == 200 and _loaded(client) == ["two"]
            one.write_bytes((setup["base"] / "panda.pt").read_bytes())  # other weights
            for _ in range(2):
                detail = assert_error(label("one"), 503)
                assert (
                    detail.startswith("Model one cannot be loaded again: ")
                    and started[:16] in detail
                )
            one.write_bytes((setup["base"] / "one.pt").read_bytes()[:1000])  # truncated
            detail = assert_error(label("one"), 503)
            assert "1,000 bytes" in detail and started[:16] in detail
            assert (
                client.get("/v1/model", params={"model": "one"}).json()["checkpoint_sha256"]
                == started
            )
            assert label("two").content == _expected(setup, "two", *KITTI_SCANS[0])
    finally:
        gw.stop()
    logged = (tmp_path / "gw.log").read_text()
    assert logged.count("model one cannot be loaded again") == 2, logged
    assert "Traceback" not in logged
