"""Single scans on the Serve application: `serve deploy` of `workers.serve_app:build_app` on a
real `ray start --head`, and a real gateway process (`--serve-url`) in front of it; a Serve
application that is late, overloaded or gone (a real HTTP server that misbehaves) is a JSON 503
or 504, never a hang."""

from __future__ import annotations

import http.server
import json
import re
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
import yaml

from rangeret.cli.main import main as rangeret_main
from rangeret.dataset.profiles import load_profile
from rangeret.inference.results import ScanPrediction
from rangeret.inference.spec import InferenceSpec
from rangeret.io.scans import read_labels, read_scan
from rangeret.models.weights.hub import file_sha256 as checkpoint_sha256
from service.labelling.serve_client import ServeLabeller
from service.models.catalog import ModelCatalog, ModelEntry
from tests.support.gateway import AUTH, OCTET, assert_error, gateway_env, start_gateway
from tests.support.open_audit import Audit
from tests.support.paths import data_path
from tests.support.workers import build_tree, free_ports, ray_node, serve_deploy, small_weights
from workers.scan_wire import (
    CONFIDENCE_HEADER,
    POINTS_HEADER,
    decode_labels,
    encode_labels,
    query_flag,
)

NET_ARGS = {"height": 32, "width": 256, "device": "cpu"}
#: The same network options as the gateway's command line takes them.
GATEWAY_NET = ["--height", "32", "--width", "256", "--device", "cpu"]
#: The applications the failed-deployment test adds beside the good one.
BAD_APPS = ("broken", "unknown")


# The exchange and the builder, without a cluster ----------------------------------------------


def test_the_exchange_round_trips_labels_and_confidences():
    labels = np.array([0, 10, 40, 252, 65536 + 10], np.uint32)
    for confidence in (None, np.linspace(0, 1, 5, dtype=np.float32)):
        body, headers = encode_labels(ScanPrediction(labels, confidence))
        back = decode_labels(body, headers, len(labels))
        assert np.array_equal(back.labels, labels)
        assert (back.confidence is None) == (confidence is None)
        if confidence is not None:
            assert np.array_equal(back.confidence, confidence)
    body, headers = encode_labels(ScanPrediction(labels))
    with pytest.raises(ValueError, match=r"answered 20 bytes for 5 points, not the 24 bytes"):
        decode_labels(body, headers, 6)
    with pytest.raises(ValueError, match=r"not the 40 bytes"):
        decode_labels(body, {**headers, CONFIDENCE_HEADER: "1"}, 5)
    assert headers[POINTS_HEADER] == "5"
    with pytest.raises(ValueError, match=rf"answered 20 bytes without the {POINTS_HEADER} header"):
        decode_labels(body, {CONFIDENCE_HEADER: "0"}, 5)
    assert query_flag("False", True, "knn") is False and query_flag(None, True, "knn") is True
    with pytest.raises(ValueError, match="the query parameter knn is true or false"):
        query_flag("maybe", True, "knn")


def test_the_builder_names_a_bad_argument_before_any_replica_starts(tmp_path):
    from workers.serve_app import DEPLOYMENT, build_app

    where = "of the rangeret Serve application"
    with pytest.raises(ValueError, match=rf"^unknown network option heigth {where}; the known"):
        build_app({"heigth": 32})
    with pytest.raises(ValueError, match=rf"^device {where} must be one of auto, cpu, cuda"):
        build_app({"device": "tpu"})
    with pytest.raises(ValueError, match=rf"^knn {where} takes true or false, got 'no'"):
        build_app({"knn": "no", "device": "cpu"})
    with pytest.raises(ValueError, match=rf"^batch_size {where} takes an integer, got 'eight'"):
        build_app({"batch_size": "eight"})
    with pytest.raises(ValueError, match=r"^batch_wait_ms must not be negative"):
        build_app({"batch_wait_ms": -1})
    missing = tmp_path / "gone.pt"
    with pytest.raises(ValueError, match=rf"^model default {where}: .*{missing}"):
        build_app({"checkpoint": str(missing), "device": "cpu"})
    weights = small_weights(tmp_path)
    app = build_app({"checkpoint": str(weights), "batch_size": 4, "device": "cpu", "knn": False})
    deployment = app._bound_deployment
    assert deployment.name == DEPLOYMENT
    assert deployment.max_ongoing_requests == 8  # one batch running, one gathering
    assert deployment.ray_actor_options["num_gpus"] == 0
    models, built, per_replica = app._bound_deployment.init_args  # what each replica gets
    assert models == {
        "default": "default",
        "models": {"default": {"checkpoint": str(weights), "device": "cpu", "knn": False}},
    }
    assert built == {
        "default": {
            "checkpoint_sha256": checkpoint_sha256(weights),
            "profile": "semantickitti",
            "network": "rangeret-cir",
        }
    }
    assert per_replica == 1
    cuda = build_app({"checkpoint": str(weights), "device": "cuda"})._bound_deployment
    assert cuda.ray_actor_options["num_gpus"] == 1


def test_the_builder_reads_several_models_as_a_models_file_does(tmp_path):
    """`models` as a mapping with `default`, or as a models file's path; the other options are
    the entries' defaults; every mistake is one sentence before any replica starts."""
    from workers.serve_app import build_app
    from workers.serve_arguments import read_arguments

    weights = small_weights(tmp_path)
    other = tmp_path / "other.pt"
    other.write_bytes(weights.read_bytes() + b"")
    entries = {"one": {"checkpoint": str(weights)}, "two": {"checkpoint": str(other), "knn": False}}
    checked = read_arguments(
        {"models": entries, "default": "two", **NET_ARGS, "batch_size": 3, "batch_wait_ms": 4}
    )
    assert checked.models.default == "two" and checked.models.names == ["one", "two"]
    assert checked.models.spec("two").knn is False and checked.models.spec("one").height == 32
    assert (checked.batch_size, checked.batch_wait_ms, checked.max_per_replica) == (3, 4.0, 2)
    path = tmp_path / "models.yaml"
    path.write_text(yaml.safe_dump({"default": "one", "models": entries}))
    from_file = read_arguments({"models": str(path), **NET_ARGS, "max_num_models_per_replica": 1})
    assert from_file.models.default == "one" and from_file.max_per_replica == 1
    assert from_file.models.spec("two") == checked.models.spec("two").replace(batch_size=1)

    where = "of the rangeret Serve application"
    bad = [
        ({"models": entries}, "default: is missing; name one of one, two"),
        ({"models": entries, "default": "three"}, "default: 'three' is not one of the models"),
        ({"default": "one"}, f"default {where} goes with models, which is not given"),
        ({"models": str(path), "default": "one"}, f"default {where} is the models file's own"),
        ({"models": {"One": {}}}, "'One' is not a model name"),
        ({"models": {"a": {"batch_size": 2}}}, "models.a.batch_size: is the server's setting"),
        (
            {"models": entries, "default": "one", "max_num_models_per_replica": 0},
            f"max_num_models_per_replica {where} takes a whole number from 1, got 0",
        ),
        ({"models": str(tmp_path / "none.yaml")}, "cannot read the models file"),
    ]
    for args, sentence in bad:
        with pytest.raises(ValueError, match=re.escape(sentence)):
            read_arguments(args)
    app = build_app({"models": entries, "default": "two", **NET_ARGS})
    _, built, per_replica = app._bound_deployment.init_args
    assert built["one"]["checkpoint_sha256"] == built["two"]["checkpoint_sha256"]
    assert per_replica == 2


# A real Serve application behind a real gateway -----------------------------------------------


@pytest.fixture(scope="module")
def deployed(tmp_path_factory) -> Iterator[dict]:
    """A head node with the Serve application deployed from a config file, as an operator does."""
    tmp = tmp_path_factory.mktemp("serve")
    weights = small_weights(tmp)
    multi = {
        "one": _copy(weights, tmp / "multi-one.pt"),
        "two": _other(weights, tmp / "multi-two.pt"),
    }
    (port,) = free_ports(1)
    config = {
        "http_options": {"host": "127.0.0.1", "port": port},
        "applications": [
            {
                "name": "rangeret",
                "route_prefix": "/rangeret",
                "import_path": "workers.serve_app:build_app",
                "args": {"checkpoint": str(weights), **NET_ARGS, "batch_size": 2},
                "deployments": [{"name": "ScanModel", "num_replicas": 1}],
            },
            {
                "name": "multi",
                "route_prefix": "/multi",
                "import_path": "workers.serve_app:build_app",
                "args": {
                    "models": {name: {"checkpoint": str(path)} for name, path in multi.items()},
                    "default": "two",
                    "max_num_models_per_replica": 1,
                    **NET_ARGS,
                    "batch_size": 2,
                },
                "deployments": [{"name": "ScanModel", "num_replicas": 1}],
            },
        ],
    }
    path = tmp / "serve.yaml"
    path.write_text(yaml.safe_dump(config))
    audit = Audit(tmp / "audit.log", (weights.name,))
    with ray_node(tmp, num_cpus=3, base_env=audit.env()) as head:
        url = f"http://127.0.0.1:{port}/rangeret"
        serve_deploy(head, path, [url, f"http://127.0.0.1:{port}/multi"])
        yield {
            "url": url,
            "multi_url": f"http://127.0.0.1:{port}/multi",
            "multi": multi,
            "weights": weights,
            "tmp": tmp,
            "head": head,
            "config": config,
            "audit": audit,
        }


def _copy(weights: Path, path: Path) -> Path:
    path.write_bytes(weights.read_bytes())
    return path


def _other(weights: Path, path: Path) -> Path:
    """The weights with their first tensor changed: another checkpoint of the same network."""
    import torch

    state = torch.load(weights, weights_only=True)
    first = next(iter(state))
    state[first] = state[first] + 1
    torch.save(state, path)
    return path


@pytest.fixture(scope="module")
def gateway(deployed):
    tmp = deployed["tmp"]
    env = gateway_env(tmp / "state", [tmp], RANGERET_SERVE_URL=deployed["url"])
    gw = start_gateway(deployed["weights"], env, tmp / "gateway.log")
    yield gw
    gw.stop()


@pytest.mark.slow
def test_scans_through_serve_get_rangeret_predicts_labels(deployed, gateway, tmp_path):
    data = build_tree(tmp_path / "data", labelled=2, unlabelled=1)
    argv = ["predict", "-q", "--dataset", str(data), "--out", str(tmp_path / "pred")]
    net = ["--checkpoint", str(deployed["weights"]), "--height", "32", "--width", "256"]
    assert rangeret_main([*argv, "--sequences", "08", "11", *net, "--device", "cpu"]) == 0
    scans = sorted(data.rglob("*.bin"))
    with gateway.client() as client:
        for scan in scans:
            answer = client.post("/v1/scans", content=scan.read_bytes(), headers=OCTET)
            assert answer.status_code == 200, answer.text
            seq = scan.parent.parent.name
            expected = tmp_path / "pred" / "sequences" / seq / "predictions" / f"{scan.stem}.label"
            assert answer.content == expected.read_bytes()

        # Concurrent requests share the replica's batches (of 2) and keep their own labels.
        bodies = [s.read_bytes() for s in scans] * 2
        with httpx.Client(base_url=gateway.url, headers=AUTH, timeout=120) as other:
            results: list[bytes] = [b""] * len(bodies)

            def send(i: int) -> None:
                results[i] = other.post("/v1/scans", content=bodies[i], headers=OCTET).content

            threads = [threading.Thread(target=send, args=(i,)) for i in range(len(bodies))]
            for t in threads:
                t.start()
            for t in threads:
                t.join(120)
        for body, result in zip(bodies, results, strict=True):
            alone = client.post("/v1/scans", content=body, headers=OCTET).content
            assert result == alone

        sure = client.post(
            "/v1/scans?confidence=true",
            content=scans[0].read_bytes(),
            headers={**OCTET, "Accept": "application/json"},
        ).json()
        first = tmp_path / "pred" / "sequences" / "08" / "predictions" / f"{scans[0].stem}.label"
        assert sure["labels"] == read_labels(first).tolist()
        confidence = np.asarray(sure["confidence"])
        assert confidence.shape == (len(read_scan(scans[0])),)
        assert (confidence >= 0).all() and (confidence <= 1).all()

        health = client.get("/healthz").json()
        assert health.get("backend") == "serve" and health["status"] == "ok", health
        served = health["workers"][0]["models"]
        assert [m["id"] for m in served] == ["default"], health
        assert served[0]["checkpoint_sha256"] == health["checkpoint_sha256"], health


@pytest.mark.slow
def test_panoptic_scans_through_serve_get_rangeret_predict_panoptic_labels(
    deployed, gateway, tmp_path
):
    """`panoptic=true` reaches the replica, whose answer carries the objects: the gateway
    answers the `.label` of `rangeret predict --panoptic`, each point's object in JSON and the
    object count in `X-RangeRet-Instances`."""
    data = build_tree(tmp_path / "data", labelled=1, unlabelled=1)
    argv = ["predict", "-q", "--dataset", str(data), "--out", str(tmp_path / "pred")]
    net = ["--checkpoint", str(deployed["weights"]), "--height", "32", "--width", "256"]
    assert (
        rangeret_main([*argv, "--sequences", "08", "11", *net, "--device", "cpu", "--panoptic"])
        == 0
    )
    with gateway.client() as client:
        for scan in sorted(data.rglob("*.bin")):
            seq = scan.parent.parent.name
            expected = tmp_path / "pred" / "sequences" / seq / "predictions" / f"{scan.stem}.label"
            raw = client.post(
                "/v1/scans", params={"panoptic": "true"}, content=scan.read_bytes(), headers=OCTET
            )
            as_json = client.post(
                "/v1/scans",
                params={"panoptic": "true", "format": "json"},
                content=scan.read_bytes(),
                headers=OCTET,
            )
            assert raw.status_code == as_json.status_code == 200, (raw.text, as_json.text)
            assert raw.content == expected.read_bytes()
            labels = read_labels(expected)
            objects = np.unique(labels >> 16)
            assert raw.headers["x-rangeret-instances"] == str(np.count_nonzero(objects))
            assert as_json.json()["instances"] == (labels >> 16).tolist()


@pytest.mark.slow
def test_a_gateway_with_other_weights_than_serves_refuses_to_start(deployed, tmp_path):
    other = _other(deployed["weights"], tmp_path / "other.pt")
    env = gateway_env(tmp_path / "state", [tmp_path], RANGERET_SERVE_URL=deployed["url"])
    run = subprocess.run(
        [
            *(sys.executable, "-m", "service", "--checkpoint", str(other), "--port", "0"),
            *("--height", "32", "--width", "256", "--device", "cpu"),
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert run.returncode == 1, run.stderr[-2000:]
    message = run.stderr.strip().splitlines()[-1]
    served = checkpoint_sha256(deployed["weights"])
    assert served in message and checkpoint_sha256(other) in message, message
    assert "Traceback" not in run.stderr


# A Serve application that misbehaves ----------------------------------------------------------


class Misbehaving(http.server.ThreadingHTTPServer):
    """An HTTP server that answers `/info` as the application would, and scans as `mode` says:
    "slow" never in time, "busy" 503, "broken" 500."""

    daemon_threads = True

    def __init__(self, info: dict) -> None:
        self.info = info
        self.mode = "slow"
        super().__init__(("127.0.0.1", 0), _Handler)


class _Handler(http.server.BaseHTTPRequestHandler):
    server: Misbehaving

    def log_message(self, *args) -> None:
        pass

    def _send(self, status: int, body: bytes) -> None:
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def do_GET(self) -> None:
        self._send(200, json.dumps(self.server.info).encode())

    def do_POST(self) -> None:
        self.rfile.read(int(self.headers["Content-Length"]))
        if self.server.mode == "slow":
            time.sleep(5)
            self._send(200, b"")
        elif self.server.mode == "busy":
            self._send(503, b"Service Unavailable")
        else:
            self._send(500, json.dumps({"detail": "CUDA error: out of memory"}).encode())


@pytest.mark.slow
def test_a_replica_reads_its_checkpoint_once(deployed):
    """The builder reads the checkpoint once, for the SHA-256 `/info` lists; the one replica
    reads it once, for its network with and without kNN."""
    info = httpx.get(deployed["url"] + "/info", timeout=10).json()
    audit = deployed["audit"]
    reads = audit.reads()
    assert reads.pop(info["pid"]) == 1 and list(reads.values()) == [1], audit.lines()
    assert info["models"] == [
        {
            "id": "default",
            "checkpoint_sha256": checkpoint_sha256(deployed["weights"]),
            "profile": "semantickitti",
            "network": "rangeret-cir",
            "loaded": True,
        }
    ]
    assert info["batch_size"] == 2
    missing = httpx.post(deployed["url"] + "/nowhere", timeout=10)
    assert missing.status_code == 404
    assert missing.json() == {"detail": "No such operation: POST /rangeret/nowhere."}


@pytest.mark.slow
def test_one_replica_with_room_for_one_network_serves_two_models_in_turn(deployed, tmp_path):
    """The `multi` application (two checkpoints, `max_num_models_per_replica: 1`, one replica):
    requests alternating between the models, sent to Serve with its model header and through a
    gateway with the same models file, each get `rangeret predict`'s labels of their
    checkpoint, with one network loaded at a time; a gateway whose models file names a model the
    application lacks stops with one line."""
    data = build_tree(tmp_path / "data", labelled=1, unlabelled=1)
    scans = sorted(data.rglob("*.bin"))
    expected = {}
    for name, weights in deployed["multi"].items():
        out = tmp_path / f"pred-{name}"
        argv = ["predict", "-q", "--dataset", str(data), "--out", str(out), "--sequences", "08"]
        net = ["--checkpoint", str(weights), "--height", "32", "--width", "256", "--device", "cpu"]
        assert rangeret_main([*argv, "11", *net]) == 0
        expected[name] = {
            scan: (out / "sequences" / scan.parent.parent.name / "predictions" / scan.name)
            .with_suffix(".label")
            .read_bytes()
            for scan in scans
        }
    assert expected["one"] != expected["two"]
    url = deployed["multi_url"]
    order = ["one", "two", "two", "one", "two", "one"]
    for name, scan in zip(order, [*scans, *scans, *scans], strict=True):
        answer = httpx.post(
            url + "/scans",
            content=scan.read_bytes(),
            headers={**OCTET, "serve_multiplexed_model_id": name},
            timeout=120,
        )
        assert answer.status_code == 200, answer.text
        assert answer.content == expected[name][scan], (name, scan)
        info = httpx.get(url + "/info", timeout=10).json()
        assert [m["id"] for m in info["models"] if m["loaded"]] == [name], info
    default = httpx.post(url + "/scans", content=scans[0].read_bytes(), headers=OCTET, timeout=120)
    assert default.content == expected["two"][scans[0]]
    unknown = httpx.post(
        url + "/scans", content=b"", headers={**OCTET, "serve_multiplexed_model_id": "three"}
    )
    assert unknown.status_code == 404
    assert unknown.json() == {
        "detail": "There is no model 'three'; this application serves one, two."
    }

    models = tmp_path / "models.yaml"
    entries = {name: {"checkpoint": str(path)} for name, path in deployed["multi"].items()}
    models.write_text(yaml.safe_dump({"default": "one", "models": entries}))
    env = gateway_env(tmp_path / "state", [tmp_path], RANGERET_SERVE_URL=url)
    gw = start_gateway(None, env, tmp_path / "gateway.log", "--models", str(models))
    try:
        with gw.client() as client:
            for name, scan in zip(order, [*scans, *scans, *scans], strict=True):
                answer = client.post(
                    "/v1/scans", params={"model": name}, content=scan.read_bytes(), headers=OCTET
                )
                assert answer.status_code == 200, answer.text
                assert answer.headers["x-rangeret-model"] == name
                assert answer.content == expected[name][scan], (name, scan)
            listed = client.get("/v1/models").json()
            assert listed["default"] == "one"
            assert [m["id"] for m in listed["models"]] == ["one", "two"]
    finally:
        gw.stop()
    assert "Traceback" not in gw.output()

    entries["three"] = {"checkpoint": str(deployed["multi"]["one"])}
    models.write_text(yaml.safe_dump({"default": "one", "models": entries}))
    run = subprocess.run(
        [sys.executable, "-m", "service", "--models", str(models), "--port", "0", *GATEWAY_NET],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert run.returncode == 1, run.stderr[-2000:]
    assert (
        run.stderr.strip()
        .splitlines()[-1]
        .endswith(
            f"the Serve application at {url} serves no model three (it serves one, two): deploy it "
            "with the gateway's models file"
        )
    ), run.stderr[-2000:]


def test_a_replica_refuses_a_checkpoint_changed_since_the_build(deployed):
    """The `multi` application's model `one`, evicted by `two`, finds its checkpoint truncated
    when it is loaded again: a 503 naming the model and the digest it was built with, never
    another network's labels; with its bytes back it serves again."""
    url = deployed["multi_url"]
    path = deployed["multi"]["one"]
    built = {m["id"]: m for m in httpx.get(url + "/info", timeout=10).json()["models"]}
    scan = data_path("semantickitti-scan", "000000.bin").read_bytes()

    def label(name: str) -> httpx.Response:
        headers = {**OCTET, "serve_multiplexed_model_id": name}
        return httpx.post(url + "/scans", content=scan, headers=headers, timeout=120)

    assert label("two").status_code == 200  # `one` is evicted: one network per replica
    original = path.read_bytes()
    try:
        path.write_bytes(original[:1000])
        refused = label("one")
        assert refused.status_code == 503, refused.text
        detail = refused.json()["detail"]
        assert detail.startswith("Model one cannot be loaded again: ")
        assert built["one"]["checkpoint_sha256"][:16] in detail and "deploy it again" in detail
    finally:
        path.write_bytes(original)
    assert label("one").status_code == 200


@pytest.mark.slow
def test_a_bad_argument_fails_the_deployment_with_its_sentence(deployed):
    """`serve deploy` of an application whose `batch_size` is not a number: Serve reports the
    spec's sentence as the application's failure, and the application beside it keeps serving,
    its batch size changed in place by its `user_config` (the same replica, no second read)."""
    head, tmp = deployed["head"], deployed["tmp"]
    before = httpx.get(deployed["url"] + "/info", timeout=10).json()
    first = deployed["config"]["applications"][0]
    scan_model = {**first["deployments"][0], "user_config": {"batch_size": 3, "batch_wait_ms": 5}}
    good = {**first, "deployments": [scan_model]}
    bad = {
        **good,
        "name": "broken",
        "route_prefix": "/broken",
        "args": {**good["args"], "batch_size": "eight"},
    }
    unknown = {
        **good,
        "name": "unknown",
        "route_prefix": "/unknown",
        "args": {**good["args"], "bogus": 1},
    }
    path = tmp / "broken.yaml"
    applications = [good, *deployed["config"]["applications"][1:], bad, unknown]
    path.write_text(yaml.safe_dump({**deployed["config"], "applications": applications}))
    serve = str(head.bindir / "serve")
    subprocess.run([serve, "deploy", str(path), "-a", head.dashboard], env=head.env, check=True)
    sentence = "batch_size of the rangeret Serve application takes an integer, got 'eight'"
    deadline = time.monotonic() + 120
    status = ""
    while time.monotonic() < deadline:
        run = subprocess.run(
            [serve, "status", "-a", head.dashboard], env=head.env, capture_output=True, text=True
        )
        status = run.stdout
        apps = yaml.safe_load(status)["applications"]
        failed = [apps.get(name, {}).get("status") == "DEPLOY_FAILED" for name in BAD_APPS]
        if all(failed):
            break
        time.sleep(1)
    said = " ".join(status.split())
    assert sentence in said and "unknown network option bogus of the rangeret Serve" in said, status
    while time.monotonic() < deadline:
        after = httpx.get(deployed["url"] + "/info", timeout=10).json()
        if after["batch_size"] == 3:
            break
        time.sleep(1)
    assert after["batch_size"] == 3 and after["pid"] == before["pid"], after
    assert deployed["audit"].reads()[before["pid"]] == 1


@pytest.mark.slow
def test_a_late_busy_broken_or_gone_serve_application_is_a_json_503_or_504(tmp_path):
    weights = small_weights(tmp_path)
    served = {"checkpoint_sha256": checkpoint_sha256(weights), "profile": "semantickitti"}
    server = Misbehaving({"default": "default", "models": [{"id": "default", **served}]})
    threading.Thread(target=server.serve_forever, daemon=True).start()
    url = f"http://127.0.0.1:{server.server_address[1]}/rangeret"
    env = gateway_env(
        tmp_path / "state", [tmp_path], RANGERET_SERVE_URL=url, RANGERET_SERVE_TIMEOUT_S="1"
    )
    gw = start_gateway(weights, env, tmp_path / "gateway.log")
    scan = np.zeros((50, 4), np.float32).tobytes()
    try:
        with gw.client() as client:
            started = time.monotonic()
            detail = assert_error(client.post("/v1/scans", content=scan, headers=OCTET), 504)
            assert time.monotonic() - started < 4
            assert "did not answer within 1 s" in detail and url in detail
            server.mode = "busy"
            answer = client.post("/v1/scans", content=scan, headers=OCTET)
            assert "overloaded or has no replica ready" in assert_error(answer, 503)
            assert answer.headers["Retry-After"] == "1"
            server.mode = "broken"
            answer = client.post("/v1/scans", content=scan, headers=OCTET)
            assert "answered 500: CUDA error: out of memory" in assert_error(answer, 503)
            server.shutdown()
            server.server_close()
            answer = client.post("/v1/scans", content=scan, headers=OCTET)
            assert "cannot be reached" in assert_error(answer, 503)
            assert answer.headers["Retry-After"] == "1"
            health = client.get("/healthz")
            assert health.status_code == 503 and health.json()["backend"] == "serve"
    finally:
        gw.stop()
    assert "Traceback" not in gw.output()
    assert "HTTP Request" not in gw.output()  # no log line per request to the application


def test_a_serve_url_that_never_answers_stops_the_gateway_with_one_sentence(tmp_path):
    (port,) = free_ports(1)
    models = ModelCatalog.one(ModelEntry("default", InferenceSpec(), load_profile(None)))
    labeller = ServeLabeller(f"http://127.0.0.1:{port}/rangeret", models, 1.0)
    from rangeret.commands import CommandError

    with pytest.raises(CommandError, match=r"did not answer within 0.5 s \(ConnectError"):
        labeller.check_serves(wait_s=0.5)
