"""`rangeret serve --models` on both profiles' bundled demo weights, a real uvicorn process: each
model's note in `/v1/models` suggests weights its own profile can run (never SemanticKITTI's
published model for nuScenes), and the gateway's log warns of the demo weights, model by model."""

from __future__ import annotations

import pytest
import yaml

from rangeret.models.weights.demo import DEMO_CHECKPOINTS
from tests.support.gateway import gateway_env, start_gateway

pytestmark = pytest.mark.slow


def test_a_models_gateway_on_demo_weights_notes_and_logs_them_by_profile(tmp_path):
    models = tmp_path / "models.yaml"
    entries = {
        "kitti": {"checkpoint": str(DEMO_CHECKPOINTS["semantickitti"])},
        "nu": {"checkpoint": str(DEMO_CHECKPOINTS["nuscenes"]), "profile": "nuscenes"},
    }
    models.write_text(yaml.safe_dump({"default": "kitti", "models": entries}))
    env = gateway_env(tmp_path / "state", [tmp_path])
    log = tmp_path / "gateway.log"
    gw = start_gateway(None, env, log, "--models", str(models), net=["--device", "cpu"])
    try:
        with gw.client() as client:
            listed = {m["id"]: m for m in client.get("/v1/models").json()["models"]}
    finally:
        gw.stop()
    assert listed["kitti"]["demo_weights"] and listed["nu"]["demo_weights"]
    assert "--checkpoint rangeret-kitti-657" in listed["kitti"]["note"]
    nu = listed["nu"]["note"]
    assert "kitti" not in nu and "trained for the nuscenes profile" in nu
    printed = log.read_text()
    for name in ("kitti", "nu"):
        assert f"model {name} is using the bundled demo weights" in printed, printed[-3000:]
