"""The API description as client generators read it, in process: pinned operation ids and error
answers, one request body per operation, file answers typed as files, the same description with
or without a token; and the single-scan answer's form chosen with `format`."""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from openapi_spec_validator import validate

from rangeret.dataset.profiles import load_profile
from rangeret.inference.predictor import Predictor
from rangeret.inference.scan_worker import ScanWorker
from rangeret.inference.spec import InferenceSpec
from rangeret.io.scans import read_scan
from service.app import create_app
from service.labelling.scan_bodies import CONTENT_TYPES
from service.routes.scans import json_answer
from service.schemas import LabelFormat
from service.settings import Settings
from tests.support.apps import one_model, pooled
from tests.support.jobs import FakeExecutor
from tests.support.paths import data_path
from tests.support.workers import small_weights

TOKEN = "openapi-test-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
ERROR = {"$ref": "#/components/schemas/ErrorResponse"}

#: Every operation of the API: (method, path) -> (operation id, the error answers it can give).
OPERATIONS = {
    ("POST", "/v1/scans"): ("label_scan", {400, 401, 403, 404, 408, 413, 415, 503, 504}),
    ("POST", "/v1/jobs"): ("create_job", {400, 401, 403, 404, 408, 413, 415, 429, 503, 507}),
    ("POST", "/v1/jobs/uploads"): (
        "upload_job",
        {400, 401, 403, 404, 408, 413, 415, 429, 503, 507},
    ),
    ("GET", "/v1/jobs"): ("list_jobs", {400, 401, 503}),
    ("GET", "/v1/jobs/{job_id}"): ("get_job", {400, 401, 404, 503}),
    ("DELETE", "/v1/jobs/{job_id}"): ("cancel_job", {400, 401, 403, 404, 503, 507}),
    ("GET", "/v1/jobs/{job_id}/predictions"): ("get_job_predictions", {400, 401, 404, 409, 503}),
    ("GET", "/v1/jobs/{job_id}/report"): ("get_job_report", {400, 401, 404, 409, 503}),
    ("GET", "/v1/jobs/{job_id}/plots/{name}"): ("get_job_plot", {400, 401, 404, 409, 503}),
    ("GET", "/v1/profile"): ("get_profile", {400, 401, 404}),
    ("GET", "/v1/model"): ("get_model", {400, 401, 404}),
    ("GET", "/v1/models"): ("list_models", {400, 401}),
    ("GET", "/healthz"): ("health", {503}),
    ("GET", "/metrics"): ("get_metrics", {400}),
}


@pytest.fixture(scope="module")
def pool(tmp_path_factory) -> ScanWorker:
    """The small 32 x 256 weights, labelling in process."""
    weights = small_weights(tmp_path_factory.mktemp("openapi"))
    spec = InferenceSpec(checkpoint=str(weights), height=32, width=256, device="cpu")
    return ScanWorker(Predictor.from_spec(spec))


def _app(state: Path, pool: ScanWorker, token: str | None = TOKEN):
    settings = Settings(state_dir=state, api_token=token)
    return create_app(
        settings, pooled(pool), FakeExecutor(), models=one_model(load_profile("semantickitti"))
    )


def _description(state: Path, pool: ScanWorker, token: str | None = TOKEN) -> dict:
    with TestClient(_app(state, pool, token), base_url="http://localhost") as client:
        return client.get("/openapi.json").json()


@pytest.fixture(scope="module")
def described(pool, tmp_path_factory) -> dict:
    return _description(tmp_path_factory.mktemp("described"), pool)


def _operations(described: dict) -> dict[tuple[str, str], dict]:
    return {
        (method.upper(), path): operation
        for path, methods in described["paths"].items()
        for method, operation in methods.items()
    }


def test_operation_ids_and_error_answers_are_pinned(described):
    operations = _operations(described)
    assert set(operations) == set(OPERATIONS)
    for key, operation in operations.items():
        operation_id, errors = OPERATIONS[key]
        assert operation["operationId"] == operation_id, key
        codes = {int(code) for code in operation["responses"] if int(code) >= 400}
        assert codes == errors, key
        for code in codes:
            content = operation["responses"][str(code)]["content"]
            if key == ("GET", "/healthz"):  # its 503 answer is the health, saying what is down
                ok = operation["responses"]["200"]["content"]["application/json"]["schema"]
                assert content["application/json"]["schema"]["anyOf"] == ok["anyOf"]
            else:
                assert content == {"application/json": {"schema": ERROR}}, (key, code)


def test_the_description_is_valid_and_the_same_with_or_without_a_token(described, pool, tmp_path):
    validate(described)
    assert _description(tmp_path, pool, token=None) == described
    assert described["components"]["securitySchemes"]["HTTPBearer"]["scheme"] == "bearer"
    assert _operations(described)["GET", "/healthz"]["security"][0] == {}, "no token needed"


def test_each_operation_has_one_request_body_and_file_answers_are_files(described):
    operations = _operations(described)
    bodies = {
        key: list(op["requestBody"]["content"])
        for key, op in operations.items()
        if "requestBody" in op
    }
    assert bodies == {
        ("POST", "/v1/scans"): list(CONTENT_TYPES),
        ("POST", "/v1/jobs"): ["application/json"],
        ("POST", "/v1/jobs/uploads"): ["multipart/form-data"],
    }
    scan_bodies = operations["POST", "/v1/scans"]["requestBody"]["content"].values()
    assert {body["schema"]["format"] for body in scan_bodies} == {"binary"}
    form = described["components"]["schemas"]["ArchiveUpload"]
    assert form["required"] == ["archive"] and form["properties"]["archive"]["format"] == "binary"
    binary = {"schema": {"type": "string", "format": "binary"}}
    for key, media in (
        (("GET", "/v1/jobs/{job_id}/predictions"), "application/zip"),
        (("GET", "/v1/jobs/{job_id}/plots/{name}"), "image/png"),
    ):
        content = operations[key]["responses"]["200"]["content"]
        assert content == {media: binary, "application/octet-stream": binary}, key
    scans = operations["POST", "/v1/scans"]["responses"]["200"]["content"]
    assert list(scans) == ["application/octet-stream", "application/json"], "raw labels first"
    assert scans["application/json"]["schema"] == {"$ref": "#/components/schemas/ScanLabels"}
    (form_param,) = [
        p for p in operations["POST", "/v1/scans"]["parameters"] if p["name"] == "format"
    ]
    assert form_param["in"] == "query" and not form_param["required"]
    assert described["components"]["schemas"]["LabelFormat"]["enum"] == ["raw", "json"]


@pytest.mark.parametrize(
    ("form", "accept", "as_json"),
    [
        (None, None, False),
        (None, "application/json", True),
        (LabelFormat.json, None, True),
        (LabelFormat.json, "application/octet-stream", True),
        (LabelFormat.raw, "application/json", False),
    ],
)
def test_format_wins_over_accept(form, accept, as_json):
    assert json_answer(form, accept) is as_json


def test_format_json_answers_the_labels_in_json(pool, tmp_path):
    scan = read_scan(data_path("semantickitti-scan", "000000.bin"))[::50].copy()
    octet = {**AUTH, "Content-Type": "application/octet-stream"}
    with TestClient(_app(tmp_path, pool)) as client:
        raw = client.post("/v1/scans", content=scan.tobytes(), headers=octet)
        as_json = client.post(
            "/v1/scans",
            content=scan.tobytes(),
            headers=octet,
            params={"format": "json", "confidence": "true"},
        )
        raw_over_accept = client.post(
            "/v1/scans",
            content=scan.tobytes(),
            headers={**octet, "Accept": "application/json"},
            params={"format": "raw"},
        )
        refused = client.post(
            "/v1/scans",
            content=scan.tobytes(),
            headers=octet,
            params={"format": "raw", "confidence": "true"},
        )
        unknown = client.post(
            "/v1/scans", content=scan.tobytes(), headers=octet, params={"format": "xml"}
        )
    labels = np.frombuffer(raw.content, "<u4")
    assert raw.status_code == 200 and len(labels) == len(scan)
    assert as_json.headers["content-type"] == "application/json"
    body = as_json.json()
    assert body["labels"] == labels.tolist() and len(body["confidence"]) == len(scan)
    assert raw_over_accept.headers["content-type"] == "application/octet-stream"
    assert raw_over_accept.content == raw.content
    assert refused.status_code == 400 and "format=json" in refused.json()["detail"]
    assert unknown.status_code == 400 and "'format'" in unknown.json()["detail"]


def _archive() -> bytes:
    scan = read_scan(data_path("semantickitti-scan", "000000.bin"))[::200].copy()
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("sequences/08/velodyne/000000.bin", scan.tobytes())
    return buf.getvalue()


def test_archives_go_to_the_upload_operation_and_still_to_the_jobs_form(pool, tmp_path):
    form = {"archive": ("data.zip", _archive(), "application/zip")}
    with TestClient(_app(tmp_path, pool), headers=AUTH) as client:
        uploaded = client.post("/v1/jobs/uploads", files=form)
        legacy = client.post("/v1/jobs", files=form)
        as_bytes = client.post(
            "/v1/jobs/uploads", content=_archive(), headers={"Content-Type": "application/zip"}
        )
        as_json = client.post("/v1/jobs/uploads", json={"dataset": "data", "split": "valid"})
        other = client.post("/v1/jobs", content=b"x", headers={"Content-Type": "text/plain"})
        listed = client.get("/v1/jobs").json()["jobs"]
    for answer in (uploaded, legacy):
        assert answer.status_code == 202, answer.text
        assert answer.headers["location"] == f"/v1/jobs/{answer.json()['id']}"
    assert {job["kind"] for job in listed} == {"archive"} and len(listed) == 2
    for answer in (as_bytes, as_json):
        assert answer.status_code == 415 and "multipart/form-data" in answer.json()["detail"]
    assert other.status_code == 415 and "/v1/jobs/uploads" in other.json()["detail"]
