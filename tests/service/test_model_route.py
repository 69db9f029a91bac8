"""GET /v1/model in process: the served network's name and checkpoint, whether they are the
bundled demo weights (with the note the page shows), under the token rule; the precision it runs
at and why, there and in /healthz."""

from __future__ import annotations

import hashlib
import os

from fastapi.testclient import TestClient

from rangeret.dataset.profiles import load_profile
from rangeret.inference.runtime.device import select_device
from rangeret.inference.runtime.precision import (
    auto_choice,
    choose_precision,
    precision_reason,
)
from rangeret.inference.spec import InferenceSpec
from rangeret.models.weights.demo import DEMO_CHECKPOINT
from service.app import create_app
from service.models.catalog import ModelCatalog, ModelEntry
from service.routes.health import precision_reasons
from service.settings import Settings
from tests.support.apps import one_model, pooled

TOKEN = "model-test-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


class FakeWorker:
    """A healthy scan worker that runs `model` (at `precision` on the CPU, where given); never
    asked to label here."""

    def __init__(self, model: str = "rangeret-cir", precision: str | None = None) -> None:
        self.model = model
        self.precision = precision

    def label_requests(self, requests):
        raise AssertionError("no scan is labelled in these tests")

    def info(self):
        run = {"device": "cpu", "precision": self.precision, "backend": "torch"}
        return {"pid": os.getpid(), "model": self.model, **(run if self.precision else {})}


class FakeExecutor:
    """Never asked to run a job here."""

    backend = "fake"
    precision = "fp32"

    def predict(self, entries, dataset, sequences, out, progress, cancel, model=None):
        raise AssertionError("no job runs in these tests")


def _client(tmp_path, sha256: str | None, model: str | None) -> TestClient:
    settings = Settings(state_dir=tmp_path / "state", api_token=TOKEN)
    app = create_app(
        settings,
        pooled(FakeWorker()),
        FakeExecutor(),
        models=one_model(load_profile("semantickitti"), sha256, model),
    )
    return TestClient(app)


def test_the_demo_weights_are_named_with_how_to_serve_a_published_model(tmp_path):
    demo = hashlib.sha256(DEMO_CHECKPOINT.read_bytes()).hexdigest()
    with _client(tmp_path, demo, "rangeret-thesis") as client:
        body = client.get("/v1/model", headers=AUTH).json()
    assert body["name"] == "rangeret-thesis" and body["checkpoint_sha256"] == demo
    assert body["profile"] == "semantickitti" and body["demo_weights"] is True
    assert "simulated scenes only" in body["note"]
    assert "--checkpoint rangeret-kitti-657" in body["note"]
    assert "rangeret weights list" in body["note"]


def test_other_weights_are_not_the_demo_and_carry_no_note(tmp_path):
    with _client(tmp_path, "ab" * 32, "rangeret-cir") as client:
        answer = client.get("/v1/model", headers=AUTH)
        anonymous = client.get("/v1/model")
        described = client.get("/openapi.json").json()
    assert answer.status_code == 200
    here = choose_precision("fp32", select_device("auto"))  # the default on this machine
    assert answer.json() == {
        "id": "default",
        "name": "rangeret-cir",
        "checkpoint_sha256": "ab" * 32,
        "profile": "semantickitti",
        "demo_weights": False,
        "note": None,
        "precision": "fp32",
        "precision_reason": here.reason,
    }
    assert anonymous.status_code == 401
    schema = described["paths"]["/v1/model"]["get"]["responses"]["200"]["content"]
    assert schema["application/json"]["schema"] == {"$ref": "#/components/schemas/ServedModel"}


def test_without_a_name_the_workers_name_the_model(tmp_path):
    with _client(tmp_path, None, None) as client:
        body = client.get("/v1/model", headers=AUTH).json()
    assert body["name"] == "rangeret-cir" and body["checkpoint_sha256"] is None
    assert body["demo_weights"] is False


def test_the_precision_auto_picks_is_said_with_why_in_model_and_healthz(tmp_path):
    picked = auto_choice("cpu")
    spec = InferenceSpec(precision="auto", device="cpu")
    entry = ModelEntry("default", spec, load_profile("semantickitti"), "cd" * 32, "rangeret-cir")
    settings = Settings(state_dir=tmp_path / "state", api_token=TOKEN)
    worker = FakeWorker(precision=picked.precision)
    app = create_app(settings, pooled(worker), FakeExecutor(), models=ModelCatalog.one(entry))
    with TestClient(app) as client:
        model = client.get("/v1/model", headers=AUTH).json()
        listed = client.get("/v1/models", headers=AUTH).json()["models"]
        health = client.get("/healthz", headers=AUTH).json()
        anonymous = client.get("/healthz").json()
    reason = f"auto's pick here: {picked.reason}"
    assert (model["precision"], model["precision_reason"]) == (picked.precision, reason)
    assert (listed[0]["precision"], listed[0]["precision_reason"]) == (picked.precision, reason)
    assert (health["precision"], health["precision_reason"]) == (picked.precision, reason)
    assert health["workers"][0]["precision_reason"] == reason
    assert "precision_reason" not in anonymous and "precision" not in anonymous


def test_workers_at_several_precisions_each_say_why():
    workers = [
        {"precision": "fp32", "device": "cpu", "precision_reason": precision_reason("fp32", "cpu")},
        {"precision": "bf16", "device": "cpu", "precision_reason": precision_reason("bf16", "cpu")},
        {"precision": "bf16", "device": "cpu", "precision_reason": precision_reason("bf16", "cpu")},
    ]
    assert precision_reasons(workers) == (
        f"bf16: {precision_reason('bf16', 'cpu')}; fp32: {precision_reason('fp32', 'cpu')}"
    )
    assert precision_reasons(workers[1:]) == precision_reason("bf16", "cpu")
    assert precision_reasons([{"pid": 1}]) is None
