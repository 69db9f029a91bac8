"""Panoptic requests in process: `POST /v1/scans?panoptic=true` answers the labels and objects
`rangeret predict --panoptic` finds (raw bytes, JSON, a file body's invalid points in no object),
plain and panoptic scans of one model side by side, the one-sentence refusal of a model without
thing classes, `GET /v1/profile`'s panoptic packing, a panoptic job's zip and report, and the
helpers the answers are made with."""

from __future__ import annotations

import asyncio
import io
import json
import os
import time
import zipfile
from pathlib import Path

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from rangeret.dataset.layout import discover, prediction_path
from rangeret.dataset.profiles import load_profile
from rangeret.dataset.selection import DatasetSelection
from rangeret.evaluation.panoptic import KITTI_PANOPTIC
from rangeret.evaluation.panoptic_evaluate import evaluate_panoptic
from rangeret.inference.clouds import label_cloud
from rangeret.inference.model_set import ModelSet
from rangeret.inference.predictor import Predictor
from rangeret.inference.results import ScanPrediction
from rangeret.inference.scan_worker import ScanWorker
from rangeret.inference.settings import ClusterSettings
from rangeret.inference.spec import InferenceSpec
from rangeret.io.point_fields import to_record
from rangeret.io.point_files import decode_point_file
from rangeret.io.scans import read_labels, read_scan
from service.app import create_app
from service.jobs.executors import LocalExecutor
from service.labelling.errors import BackendError
from service.labelling.panoptic import (
    INSTANCES_HEADER,
    label_classes,
    model_clustering,
    panoptic_dtype,
    scan_objects,
)
from service.labelling.pooled import PooledLabeller
from service.labelling.serve_client import ServeLabeller
from service.models.loader import ModelLoader
from service.models.pool import ModelPool
from service.routes.profile import served_profile
from service.settings import Settings
from tests.service.panoptic_weights import panoptic_weights
from tests.support.apps import one_model, pooled
from tests.support.jobs import FakeExecutor
from tests.support.paths import data_path
from tests.support.point_files import pcd_bytes
from tests.support.workers import build_tree
from workers.scan_wire import encode_labels

TOKEN = "panoptic-test-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
OCTET = {**AUTH, "Content-Type": "application/octet-stream"}
KITTI = load_profile("semantickitti")


@pytest.fixture(scope="module")
def weights(tmp_path_factory) -> Path:
    return panoptic_weights(tmp_path_factory.mktemp("panoptic-weights"))


@pytest.fixture(scope="module")
def spec(weights) -> InferenceSpec:
    return InferenceSpec(checkpoint=str(weights), height=32, width=256, device="cpu")


@pytest.fixture(scope="module")
def worker(spec) -> ScanWorker:
    """The random 32 x 256 weights, labelling in process."""
    return ScanWorker(Predictor.from_spec(spec))


@pytest.fixture(scope="module")
def reference(spec) -> Predictor:
    """What `rangeret predict --panoptic` runs."""
    return Predictor.from_spec(spec.replace(panoptic=True))


@pytest.fixture(scope="module")
def scan() -> np.ndarray:
    return read_scan(data_path("semantickitti-scan", "000000.bin"))[::5].copy()


def _app(state: Path, worker: object, executor: object = None, profile=KITTI):
    settings = Settings(state_dir=state, api_token=TOKEN)
    labeller = pooled(worker)
    return create_app(
        settings, labeller, executor or FakeExecutor(), models=one_model(profile, "f" * 64)
    )


# Single scans -------------------------------------------------------------------------------------


def test_a_panoptic_scan_is_answered_as_predict_panoptic_labels_it(
    worker, reference, scan, tmp_path
):
    expected = reference.predict(scan)
    assert expected.num_instances > 0  # the scan has objects to find
    with TestClient(_app(tmp_path, worker)) as client:
        raw = client.post(
            "/v1/scans", content=scan.tobytes(), headers=OCTET, params={"panoptic": "true"}
        )
        as_json = client.post(
            "/v1/scans",
            content=scan.tobytes(),
            headers=OCTET,
            params={"panoptic": "true", "format": "json", "confidence": "true"},
        )
        plain = client.post("/v1/scans", content=scan.tobytes(), headers=OCTET)
        plain_json = client.post(
            "/v1/scans", content=scan.tobytes(), headers=OCTET, params={"format": "json"}
        )
    assert raw.status_code == 200, raw.text
    assert raw.content == expected.labels.astype("<u4").tobytes()
    assert raw.headers[INSTANCES_HEADER] == str(expected.num_instances)
    body = as_json.json()
    assert as_json.headers[INSTANCES_HEADER] == str(expected.num_instances)
    assert body["labels"] == expected.labels.tolist()
    assert body["instances"] == expected.instances.tolist()
    assert np.array_equal(np.asarray(body["labels"]) >> 16, body["instances"])  # instance << 16
    assert len(body["confidence"]) == len(scan)
    classes = KITTI.labels.to_class(expected.labels & 0xFFFF)
    names = KITTI.labels.class_names
    counts = np.bincount(classes, minlength=len(names))
    assert body["class_counts"] == {names[c]: int(n) for c, n in enumerate(counts) if n}
    objects = body["objects"]
    assert [o["instance"] for o in objects] == sorted(set(expected.instances.tolist()) - {0})
    for found in objects:
        points = expected.instances == found["instance"]
        assert found["points"] == int(points.sum())
        assert {names[c] for c in classes[points]} == {found["class_name"]}
        assert found["class_name"] in KITTI.thing_names
    # Plain scans of the same model are still plain, with no objects.
    assert INSTANCES_HEADER not in plain.headers and INSTANCES_HEADER not in plain_json.headers
    assert plain.content == (expected.labels & 0xFFFF).astype("<u4").tobytes()
    assert {"instances", "objects"}.isdisjoint(plain_json.json())


def test_plain_and_panoptic_scans_of_one_model_are_answered_side_by_side(worker, reference, scan):
    """The panoptic scans of a model gather behind their own batcher; both kinds are answered
    at once, each as its own kind, and the labeller's depth counts both."""
    labeller = pooled(worker)

    async def run() -> list[ScanPrediction]:
        await labeller.start()
        try:
            answers = await asyncio.gather(
                *(
                    labeller.label_points(scan, True, False, panoptic, model="default")
                    for panoptic in (False, True, False, True)
                )
            )
            assert labeller.depth() == 0
            return answers
        finally:
            await labeller.stop()

    plain, objects, plain_again, objects_again = asyncio.run(run())
    expected = reference.predict(scan)
    assert plain.instances is None and np.array_equal(plain.labels, plain_again.labels)
    assert np.array_equal(plain.labels, expected.labels & 0xFFFF)
    for answer in (objects, objects_again):
        assert np.array_equal(answer.labels, expected.labels)
        assert np.array_equal(answer.instances, expected.instances)
    runtime = labeller.pool.acquire("default")
    labeller.pool.release("default")
    assert len(runtime.batchers()) == 2 and runtime.clustering == ClusterSettings()


def test_a_file_body_s_invalid_points_are_in_no_object(worker, reference, scan, tmp_path):
    cloud = scan[:4000].copy()
    cloud[::9] = np.nan  # an organised cloud's empty returns
    body = pcd_bytes(cloud, "binary")
    decoded = decode_point_file(body, "pcd", record=KITTI.points, source="the scan")
    record = to_record(
        decoded.columns,
        record=KITTI.points,
        source="the scan",
        reflectance_fill=KITTI.reflectance_fill,
    )
    expected = label_cloud(reference, record)  # what `rangeret predict --files --panoptic` writes
    headers = {**AUTH, "Content-Type": "application/x-pcd"}
    with TestClient(_app(tmp_path, worker)) as client:
        raw = client.post("/v1/scans", content=body, headers=headers, params={"panoptic": "true"})
        as_json = client.post(
            "/v1/scans",
            content=body,
            headers=headers,
            params={"panoptic": "true", "format": "json"},
        )
    assert raw.status_code == 200, raw.text
    assert raw.content == expected.labels.astype("<u4").tobytes()
    instances = np.asarray(as_json.json()["instances"])
    assert np.array_equal(instances, expected.instances)
    assert not instances[::9].any() and not np.frombuffer(raw.content, "<u4")[::9].any()
    assert raw.headers[INSTANCES_HEADER] == str(expected.num_instances)


def test_a_model_without_thing_classes_refuses_panoptic_scans_in_one_sentence(tmp_path):
    class Unused:
        def label_requests(self, requests):
            raise AssertionError("a refused scan is never labelled")

        def info(self):
            return {"pid": os.getpid()}

    panda = load_profile("pandaset")
    scan = np.zeros((10, 5), np.float32)
    with TestClient(_app(tmp_path, Unused(), profile=panda)) as client:
        refused = client.post(
            "/v1/scans", content=scan.tobytes(), headers=OCTET, params={"panoptic": "true"}
        )
        profile = client.get("/v1/profile", headers=AUTH).json()
    assert refused.status_code == 400, refused.text
    detail = refused.json()["detail"]
    assert set(refused.json()) == {"detail"} and "\n" not in detail and detail.endswith(".")
    assert detail == (
        "The model default runs with the pandaset profile, which names no thing classes, so it "
        "has no objects to find: leave panoptic out, or use a model whose profile names its "
        "things."
    )
    assert profile["panoptic"] is None


def test_the_profile_says_how_panoptic_labels_pack_the_objects(worker, tmp_path):
    with TestClient(_app(tmp_path, worker)) as client:
        kitti = client.get("/v1/profile", headers=AUTH).json()["panoptic"]
    assert kitti == {
        "benchmark": "semantickitti-panoptic",
        "things": KITTI.thing_names,
        "label_bytes": 4,
        "multiplier": 65536,
        "instance_high": True,
    }
    nuscenes = served_profile(load_profile("nuscenes")).panoptic
    assert nuscenes.model_dump() == {
        "benchmark": "nuscenes-panoptic",
        "things": load_profile("nuscenes").thing_names,
        "label_bytes": 2,
        "multiplier": 1000,
        "instance_high": False,
    }


def test_nuscenes_panoptic_labels_are_uint16_and_name_their_class():
    nuscenes = load_profile("nuscenes")
    assert panoptic_dtype(nuscenes) == np.dtype("<u2") and panoptic_dtype(KITTI) == np.dtype("<u4")
    labels = np.array([4001, 4002, 11000, 0], dtype=np.uint32)  # two of class 4, stuff
    classes = label_classes(nuscenes, labels, panoptic=True)
    assert classes.tolist() == [4, 4, 11, 0]
    assert label_classes(nuscenes, np.array([4, 11]), panoptic=False).tolist() == [4, 11]
    instances = np.array([7, 9, 0, 0], dtype=np.uint32)
    names = nuscenes.labels.class_names
    assert scan_objects(nuscenes, classes, instances) == [(7, names[4], 1), (9, names[4], 1)]
    spec = InferenceSpec(cluster_angle=12.5, min_cluster_points=3)
    assert model_clustering(spec) == ClusterSettings(12.5, 3)


# The Serve application's answers ----------------------------------------------------------------


def _serve(answer: ScanPrediction) -> tuple[ServeLabeller, list[httpx.Request]]:
    """A Serve labeller whose application answers `answer` to every scan, and its requests."""
    asked: list[httpx.Request] = []

    def respond(request: httpx.Request) -> httpx.Response:
        asked.append(request)
        body, headers = encode_labels(answer)
        return httpx.Response(200, content=body, headers=headers)

    labeller = ServeLabeller("http://serve", one_model(KITTI), timeout=5)
    labeller._new_client = lambda: httpx.AsyncClient(transport=httpx.MockTransport(respond))
    return labeller, asked


def test_the_serve_labeller_asks_for_objects_and_checks_they_come():
    labels = np.array([10 | 1 << 16, 40, 40], dtype=np.uint32)
    with_objects = ScanPrediction(labels, instances=np.array([1, 0, 0], dtype=np.uint32))
    points = np.zeros((3, 4), np.float32)

    async def label(answer: ScanPrediction, panoptic: bool) -> tuple[ScanPrediction, httpx.Request]:
        labeller, asked = _serve(answer)
        await labeller.start()
        try:
            found = await labeller.label_points(points, panoptic=panoptic, model="default")
        finally:
            await labeller.stop()
        return found, asked[0]

    found, request = asyncio.run(label(with_objects, True))
    assert request.url.params["panoptic"] == "true" and found.num_instances == 1
    assert found.instances.tolist() == [1, 0, 0] and found.labels.tolist() == labels.tolist()
    _, plain = asyncio.run(label(ScanPrediction(labels & 0xFFFF), False))
    assert plain.url.params["panoptic"] == "false"
    with pytest.raises(BackendError, match="without the scan's objects"):
        asyncio.run(label(ScanPrediction(labels), True))


# Jobs -----------------------------------------------------------------------------------------------


def test_a_panoptic_job_zips_and_scores_as_the_panoptic_benchmark(worker, reference, tmp_path):
    """An archive job with `?panoptic=true` and a dataset job with `"panoptic": true` write what
    `rangeret predict --panoptic` writes, zip it as SemanticKITTI panoptic wants it and score it
    as `rangeret evaluate --panoptic` does; a panoptic job of a model without things is a 400."""
    roots = tmp_path / "roots"
    tree = build_tree(roots / "data", labelled=2, unlabelled=0)
    labeller = pooled(worker)
    executor = LocalExecutor(labeller.pool, "default")
    settings = Settings(state_dir=tmp_path / "state", api_token=TOKEN, data_roots=[roots])
    app = create_app(settings, labeller, executor, models=one_model(KITTI, "f" * 64))
    archive = io.BytesIO()
    with zipfile.ZipFile(archive, "w") as zf:
        for path in sorted(tree.rglob("*")):
            zf.write(path, path.relative_to(tree).as_posix())
    with TestClient(app, headers=AUTH) as client:
        uploaded = client.post(
            "/v1/jobs/uploads",
            params={"panoptic": "true"},
            files={"archive": ("data.zip", archive.getvalue(), "application/zip")},
        )
        named = client.post(
            "/v1/jobs", json={"dataset": "data", "sequences": ["08"], "panoptic": True}
        )
        assert uploaded.status_code == named.status_code == 202, (uploaded.text, named.text)
        done = [_wait(client, answer.json()["id"]) for answer in (uploaded, named)]
        zips = [client.get(f"/v1/jobs/{job['id']}/predictions").content for job in done]
        reports = [client.get(f"/v1/jobs/{job['id']}/report").json() for job in done]
    selection = discover(tree, ["08"], layout=KITTI.layout, panoptic=True)
    truth_has_objects = any((read_labels(e.label_path) >> 16).any() for e in selection.scans)
    assert truth_has_objects
    for job, zipped, report in zip(done, zips, reports, strict=True):
        assert job["state"] == "succeeded" and job["panoptic"] is True, job
        assert job["plots"] == []
        with zipfile.ZipFile(io.BytesIO(zipped)) as zf:
            for entry in selection.scans:
                member = f"sequences/08/predictions/{entry.name}.label"
                expected = reference.predict(read_scan(entry.scan_path))
                assert np.frombuffer(zf.read(member), "<u4").tolist() == expected.labels.tolist()
        assert report["task"] == "panoptic" and report["benchmark"] == "semantickitti-panoptic"
        assert report["headline"]["pq"] == pytest.approx(job["metrics"]["pq"])
        assert report["precision"] == "fp32" and report["backend"] == "torch"
        assert set(report["classes"]) >= set(KITTI.thing_names)
        assert job["metrics"]["miou"] == pytest.approx(report["iou_mean"])
    # The dataset job's predictions are scored as `rangeret evaluate --panoptic` scores them.
    folder = tmp_path / "state" / "jobs" / done[1]["id"] / "predictions"
    scored = evaluate_panoptic(
        DatasetSelection(tree, ("08",), KITTI.layout, panoptic=True),
        folder,
        profile=KITTI,
        rules=KITTI_PANOPTIC,
        benchmark="semantickitti-panoptic",
        checkpoint_sha256="f" * 64,
    ).to_dict()
    for key, value in scored.items():
        assert reports[1][key] == value, key
    assert prediction_path(folder, "08", "000000").is_file()


def test_a_panoptic_job_of_a_model_without_things_is_refused(tmp_path):
    roots = tmp_path / "roots"
    (roots / "panda").mkdir(parents=True)
    settings = Settings(state_dir=tmp_path / "state", api_token=TOKEN, data_roots=[roots])
    panda = load_profile("pandaset")
    app = create_app(settings, pooled(object()), FakeExecutor(), models=one_model(panda))
    with TestClient(app, headers=AUTH) as client:
        named = client.post(
            "/v1/jobs", json={"dataset": "panda", "sequences": ["1"], "panoptic": True}
        )
        uploaded = client.post(
            "/v1/jobs/uploads",
            params={"panoptic": "true"},
            files={"archive": ("data.zip", b"PK\x05\x06" + b"\0" * 18, "application/zip")},
        )
        jobs = client.get("/v1/jobs").json()["jobs"]
    for answer in (named, uploaded):
        assert answer.status_code == 400, answer.text
        assert "names no thing classes" in answer.json()["detail"]
    assert jobs == [] and not any((tmp_path / "state" / "jobs").glob("*"))


def _wait(client: TestClient, job_id: str, timeout: float = 120) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        status = client.get(f"/v1/jobs/{job_id}").json()
        if status["state"] in ("succeeded", "failed", "cancelled"):
            return status
        time.sleep(0.1)
    raise AssertionError(f"job {job_id} did not finish: {json.dumps(status)}")


def test_a_model_loaded_with_panoptic_options_answers_plain_scans_plainly(spec, scan):
    """A models-file entry with `panoptic: true` and its clustering options: plain requests and
    jobs get plain labels (its predictor finds no objects), panoptic ones get the objects its
    options find, as `rangeret predict --panoptic` with the same options does."""
    options = spec.replace(panoptic=True, cluster_angle=25.0, min_cluster_points=3)
    loader = ModelLoader(ModelSet({"default": options}, "default"))
    runtime = loader("default")
    assert runtime.predictor.clustering is None
    assert runtime.clustering == ClusterSettings(25.0, 3)
    labeller = PooledLabeller(ModelPool(["default"], lambda _: runtime))

    async def run() -> list[ScanPrediction]:
        await labeller.start()
        try:
            return [
                await labeller.label_points(scan, panoptic=panoptic, model="default")
                for panoptic in (False, True)
            ]
        finally:
            await labeller.stop()

    plain, objects = asyncio.run(run())
    expected = Predictor.from_spec(options).predict(scan)
    default = Predictor.from_spec(spec.replace(panoptic=True)).predict(scan)
    assert plain.instances is None and np.array_equal(plain.labels, expected.labels & 0xFFFF)
    assert np.array_equal(objects.instances, expected.instances)
    assert np.array_equal(objects.labels, expected.labels)
    assert not np.array_equal(expected.instances, default.instances)  # the options count


def test_the_api_description_names_the_panoptic_flags_header_and_fields(worker, tmp_path):
    with TestClient(_app(tmp_path, worker)) as client:
        described = client.get("/openapi.json").json()
    paths, schemas = described["paths"], described["components"]["schemas"]

    def query(path: str, method: str = "post") -> dict:
        params = paths[path][method]["parameters"]
        return next(p for p in params if p["name"] == "panoptic" and p["in"] == "query")

    for path in ("/v1/scans", "/v1/jobs/uploads"):
        flag = query(path)
        assert flag["schema"]["type"] == "boolean" and flag["schema"]["default"] is False
        assert not flag["required"] and flag["description"]
    answer = paths["/v1/scans"]["post"]["responses"]["200"]
    assert answer["headers"][INSTANCES_HEADER]["schema"] == {"type": "integer", "minimum": 0}
    assert {"instances", "objects"} <= set(schemas["ScanLabels"]["properties"])
    assert set(schemas["ScanObject"]["required"]) == {"instance", "class_name", "points"}
    assert schemas["DatasetJobRequest"]["properties"]["panoptic"]["default"] is False
    assert {"pq", "sq", "rq", "pq_dagger"} <= set(schemas["JobMetrics"]["properties"])
    assert "panoptic" in schemas["JobStatus"]["properties"]
    assert "panoptic" in schemas["ServedProfile"]["properties"]
