"""Panoptic requests against a real `rangeret serve` (uvicorn) of three models: SemanticKITTI
(random 32 x 256 weights that find dozens of objects), nuScenes and PandaSet (no thing classes).

A scan with `panoptic=true` is answered with the file `rangeret predict --panoptic` writes for it
(SemanticKITTI's uint32 `.label`, nuScenes-panoptic's uint16 values), its JSON form with each
point's object and `X-RangeRet-Instances` with the object count; a dataset job and an archive job
with `panoptic` zip the panoptic benchmark's archive of the same labels and report what
`rangeret evaluate --panoptic --json` reports; the PandaSet model refuses both in one sentence.
"""

from __future__ import annotations

import io
import json
import zipfile
from collections.abc import Iterator

import numpy as np
import pytest
import torch
import yaml

from rangeret.cli.main import main as rangeret_main
from rangeret.dataset.layout import discover
from rangeret.dataset.profiles import load_profile
from rangeret.io.panoptic_labels import read_panoptic_npz
from rangeret.models import build_model
from rangeret.submission.nuscenes import validate_nuscenes_submission
from rangeret.submission.nuscenes_format import PANOPTIC_RESULTS
from tests.service.panoptic_weights import panoptic_weights
from tests.support.gateway import (
    NET,
    OCTET,
    Gateway,
    assert_error,
    gateway_env,
    start_gateway,
    wait_job,
)
from tests.support.nuscenes import entries, network, write_tree
from tests.support.workers import build_tree

KITTI = load_profile("semantickitti")
NUSCENES = load_profile("nuscenes")
SCENES = {"scene-0103": 1, "scene-0916": 1}  # nuScenes' mini_val
INSTANCES = "x-rangeret-instances"


def _cli(*args: str) -> None:
    """A `rangeret` command run here, on one torch thread (the labels do not depend on it)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert rangeret_main([*args, "-q"]) == 0, args
    finally:
        torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A SemanticKITTI tree (08 with panoptic ground truth, 11 without), a simulated nuScenes
    mini_val with nuScenes-panoptic ground truth, `rangeret predict --panoptic` and `rangeret
    evaluate --panoptic --json` of both, and the models file (`kitti` the default)."""
    base = tmp_path_factory.mktemp("panoptic-gateway")
    roots = base / "roots"
    kitti_tree = build_tree(roots / "kitti", labelled=2, unlabelled=1)
    nu_tree = write_tree(roots / "nu", SCENES)
    kitti = panoptic_weights(base)
    torch.save(network(0).state_dict(), base / "nu.pt")
    torch.manual_seed(0)
    panda = base / "panda.pt"
    torch.save(build_model("rangeret-cir", 32, 256, num_classes=15, layers=1).state_dict(), panda)

    kitti_net = ["--checkpoint", str(kitti), *NET, "--panoptic"]
    nu_net = ["--profile", "nuscenes", "--checkpoint", str(base / "nu.pt"), *NET, "--panoptic"]
    kitti_data = ["--dataset", str(kitti_tree), "--sequences"]
    _cli("predict", *kitti_data, "08", "11", "--out", str(base / "ref-kitti"), *kitti_net)
    nu_data = ["--dataset", str(nu_tree), "--split", "mini_val"]
    _cli("predict", *nu_data, "--out", str(base / "ref-nu"), *nu_net)
    reports = {}
    for name, data, extra in (
        ("kitti", [*kitti_data, "08"], []),
        ("nu", nu_data, ["--profile", "nuscenes"]),
    ):
        reports[name] = base / f"{name}-report.json"
        _cli(
            "evaluate",
            *data,
            *extra,
            "--panoptic",
            "--predictions",
            str(base / f"ref-{name}"),
            "--json",
            str(reports[name]),
        )

    models = base / "models.yaml"
    entries_ = {
        "kitti": {"checkpoint": str(kitti)},
        "nu": {"checkpoint": str(base / "nu.pt"), "profile": "nuscenes"},
        "panda": {"checkpoint": str(panda), "profile": "pandaset"},
    }
    models.write_text(yaml.safe_dump({"default": "kitti", "models": entries_}, sort_keys=False))
    return {
        "base": base,
        "roots": roots,
        "kitti": kitti_tree,
        "nu": nu_tree,
        "ref-kitti": base / "ref-kitti",
        "ref-nu": base / "ref-nu",
        "reports": {k: json.loads(v.read_text()) for k, v in reports.items()},
        "models": models,
    }


@pytest.fixture(scope="module")
def gateway(setup: dict) -> Iterator[Gateway]:
    env = gateway_env(setup["base"] / "state", [setup["roots"]], RANGERET_MAX_ARCHIVE_MEMBERS="100")
    gw = start_gateway(None, env, setup["base"] / "gateway.log", "--models", str(setup["models"]))
    yield gw
    gw.stop()


def _kitti_scans(setup: dict) -> list:
    return discover(setup["kitti"], ["08", "11"], layout=KITTI.layout, panoptic=True).scans


def _zipped(client, job_id: str) -> dict[str, bytes]:
    """A job's predictions zip, its files by name."""
    answer = client.get(f"/v1/jobs/{job_id}/predictions")
    assert answer.status_code == 200, answer.text
    with zipfile.ZipFile(io.BytesIO(answer.content)) as zf:
        return {n: zf.read(n) for n in zf.namelist() if not n.endswith("/")}


# Single scans -----------------------------------------------------------------------------------


def test_kitti_scans_are_answered_with_the_labels_predict_panoptic_writes(setup, gateway):
    scans = _kitti_scans(setup)
    with gateway.client() as client:
        raw = [
            client.post(
                "/v1/scans",
                content=e.scan_path.read_bytes(),
                headers=OCTET,
                params={"panoptic": "true"},
            )
            for e in scans
        ]
        as_json = client.post(
            "/v1/scans",
            content=scans[0].scan_path.read_bytes(),
            headers={**OCTET, "Accept": "application/json"},
            params={"panoptic": "true"},
        )
        plain = client.post("/v1/scans", content=scans[0].scan_path.read_bytes(), headers=OCTET)
    for entry, answer in zip(scans, raw, strict=True):
        assert answer.status_code == 200, answer.text
        written = entry.prediction_in(setup["ref-kitti"]).read_bytes()
        assert answer.content == written, entry.key
        objects = np.unique(np.frombuffer(written, "<u4") >> 16)
        assert answer.headers[INSTANCES] == str(np.count_nonzero(objects)), entry.key
    labels = np.frombuffer(raw[0].content, "<u4")
    body = as_json.json()
    assert body["labels"] == labels.tolist() and body["instances"] == (labels >> 16).tolist()
    assert as_json.headers[INSTANCES] == raw[0].headers[INSTANCES] != "0"
    assert len(body["objects"]) == int(raw[0].headers[INSTANCES])
    assert {o["class_name"] for o in body["objects"]} <= set(KITTI.thing_names)
    assert sum(o["points"] for o in body["objects"]) == int(np.count_nonzero(labels >> 16))
    assert INSTANCES not in plain.headers
    assert plain.content == (labels & 0xFFFF).astype("<u4").tobytes()


def test_nuscenes_scans_are_answered_with_the_panoptic_values_predict_writes(setup, gateway):
    mini_val = entries(setup["nu"], list(SCENES), split="mini_val", panoptic=True)
    with gateway.client() as client:
        answers = [
            client.post(
                "/v1/scans",
                params={"model": "nu", "panoptic": "true", "format": "json"},
                content=e.scan_path.read_bytes(),
                headers=OCTET,
            )
            for e in mini_val
        ]
        raw = client.post(
            "/v1/scans",
            params={"model": "nu", "panoptic": "true"},
            content=mini_val[0].scan_path.read_bytes(),
            headers=OCTET,
        )
    found = 0
    for entry, answer in zip(mini_val, answers, strict=True):
        assert answer.status_code == 200, answer.text
        written = read_panoptic_npz(entry.prediction_in(setup["ref-nu"]))
        body = answer.json()
        assert body["labels"] == written.tolist()
        instances = np.asarray(body["instances"])
        # A scan-unique object is one (class, number in its class) of the panoptic values.
        assert np.array_equal(instances > 0, written % 1000 > 0)
        pairs = {(int(i), int(v)) for i, v in zip(instances, written, strict=True) if i}
        assert len(pairs) == len({i for i, _ in pairs}) == len({v for _, v in pairs})
        assert answer.headers[INSTANCES] == str(len(pairs))
        found += len(pairs)
        classes = written // 1000
        names = NUSCENES.labels.class_names
        counts = np.bincount(classes, minlength=len(names))
        assert body["class_counts"] == {names[c]: int(n) for c, n in enumerate(counts) if n}
    assert found > 0
    assert raw.content == read_panoptic_npz(mini_val[0].prediction_in(setup["ref-nu"])).tobytes()
    assert len(raw.content) == 2 * answers[0].json()["num_points"]  # uint16 values


def test_a_model_without_thing_classes_refuses_panoptic_scans_and_jobs(setup, gateway):
    body = np.zeros((10, 5), np.float32).tobytes()
    with gateway.client() as client:
        scan = client.post(
            "/v1/scans", params={"model": "panda", "panoptic": "true"}, content=body, headers=OCTET
        )
        job = client.post(
            "/v1/jobs",
            json={"dataset": "kitti", "sequences": ["1"], "model": "panda", "panoptic": True},
        )
        upload = client.post(
            "/v1/jobs/uploads",
            params={"model": "panda", "panoptic": "true"},
            files={"archive": ("a.zip", b"not read", "application/zip")},
        )
        plain = client.post("/v1/scans", params={"model": "panda"}, content=body, headers=OCTET)
        profile = client.get("/v1/profile", params={"model": "panda"}).json()
    sentence = (
        "The model panda runs with the pandaset profile, which names no thing classes, so it "
        "has no objects to find: leave panoptic out, or use a model whose profile names its "
        "things."
    )
    for answer in (scan, job, upload):
        assert assert_error(answer, 400) == sentence
    assert plain.status_code == 200 and profile["panoptic"] is None


# Jobs -------------------------------------------------------------------------------------------


def test_kitti_panoptic_jobs_zip_and_score_what_predict_and_evaluate_panoptic_do(setup, gateway):
    tree = setup["kitti"]
    upload = io.BytesIO()
    with zipfile.ZipFile(upload, "w") as zf:
        for path in sorted((tree / "sequences" / "08").rglob("*")):
            zf.write(path, path.relative_to(tree).as_posix())
    with gateway.client() as client:
        named = client.post(
            "/v1/jobs", json={"dataset": "kitti", "sequences": ["08", "11"], "panoptic": True}
        )
        uploaded = client.post(
            "/v1/jobs/uploads",
            params={"panoptic": "true"},
            files={"archive": ("kitti.zip", upload.getvalue(), "application/zip")},
        )
        assert named.status_code == uploaded.status_code == 202, (named.text, uploaded.text)
        done = [wait_job(client, a.json()["id"]) for a in (named, uploaded)]
        zips = [_zipped(client, job["id"]) for job in done]
        reports = [client.get(f"/v1/jobs/{job['id']}/report").json() for job in done]
    expected = {
        f"sequences/{e.sequence}/predictions/{e.name}.label": e.prediction_in(
            setup["ref-kitti"]
        ).read_bytes()
        for e in _kitti_scans(setup)
    }
    reference = setup["reports"]["kitti"]
    for job, files, report in zip(done, zips, reports, strict=True):
        assert job["state"] == "succeeded" and job["panoptic"] is True, job
        labels = {n: data for n, data in files.items() if n.endswith(".label")}
        assert labels == {n: d for n, d in expected.items() if n in labels}
        assert report["task"] == "panoptic" and report["precision"] == "fp32"
        for key in ("pq_mean", "pq_dagger", "sq_mean", "rq_mean", "iou_mean", "classes"):
            assert report[key] == reference[key], key
        assert report["per_sequence"] == reference["per_sequence"]
        assert report["per_distance"] == reference["per_distance"]
        assert job["metrics"]["pq"] == pytest.approx(reference["pq_mean"])
        assert job["metrics"]["miou"] == pytest.approx(reference["iou_mean"])
    assert len(zips[0]) - 1 == 3 and len(zips[1]) - 1 == 2  # and description.txt


def test_a_nuscenes_panoptic_job_zips_the_nuscenes_panoptic_results_folder(setup, gateway):
    request = {
        "dataset": "nu",
        "model": "nu",
        "split": "mini_val",
        "version": "v1.0-mini",
        "panoptic": True,
    }
    with gateway.client() as client:
        created = client.post("/v1/jobs", json=request)
        assert created.status_code == 202, created.text
        status = wait_job(client, created.json()["id"])
        files = _zipped(client, status["id"])
        zipped = client.get(f"/v1/jobs/{status['id']}/predictions").content
        report = client.get(f"/v1/jobs/{status['id']}/report").json()
    assert status["state"] == "succeeded" and status["panoptic"] is True, status
    ref = setup["ref-nu"]
    expected = {p.relative_to(ref).as_posix() for p in ref.rglob("*_panoptic.npz")}
    assert {n for n in files if n.endswith(".npz")} == expected and len(expected) == 2
    for name in expected:
        values = read_panoptic_npz(name, data=files[name])
        assert np.array_equal(values, read_panoptic_npz(ref / name)), name
    archive = setup["base"] / "panoptic-job.zip"
    archive.write_bytes(zipped)
    check = validate_nuscenes_submission(
        archive, setup["nu"], "mini_val", profile=NUSCENES, results=PANOPTIC_RESULTS
    )
    assert check.problems == [] and check.scans == 2
    reference = setup["reports"]["nu"]
    assert report["task"] == "panoptic" and report["benchmark"] == "nuscenes-panoptic"
    assert report["all"] == reference["all"] and report["per_sequence"] == reference["per_sequence"]
    assert status["metrics"]["pq"] == pytest.approx(reference["all"]["PQ"])
    assert status["plots"] == []
