"""The documented cluster, brought up the way KubeRay brings it up, on one machine.

`deploy/kuberay/rayservice.yaml`'s head and its GPU worker group (two nodes) are started with the
commands KubeRay composes for their containers (`tests/support/kuberay.py`: the container's command and
args, then `ulimit` and the `ray start` built from rayStartParams and the container's resources,
run by `/bin/bash -c --`), with the environment KubeRay gives the pods (authOptions' token from
`secrets.example.yaml`) and the project's environment in place of the image. The Serve config of
the RayService is deployed with `serve deploy`, and the gateway is started with the Deployment's
args and environment through `deploy/entrypoint.sh`, as the image starts it.

What the test changes, so that three nodes fit on one machine: port numbers (and the ports Ray
picks itself, so that two nodes on one host never share one), CPU, GPU and memory quantities
(two logical GPUs per worker node, so that the network runs on the CPU), the Serve deployment's
replica counts and autoscaling delays, the volume mounts (`/data`, `/models`, `/results` and the
models file's `/etc/rangeret` are folders of the test, the file's checkpoint paths mapped to
them), the service names (mapped to loopback), and the weights: small networks at 32 x 256 in
place of the published ones, with their resolution added to the arguments of both the Serve
application and the gateway.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import pytest
import torch
import yaml

from rangeret.cli.main import main as rangeret_main
from rangeret.dataset.labels import semantickitti
from rangeret.dataset.layout import prediction_path
from rangeret.dataset.profiles import load_profile
from rangeret.models import build_model
from rangeret.sim import simulate_dataset
from rangeret.submission.archives import validate_submission
from tests.support.gateway import OCTET, Gateway, wait_healthy, wait_job
from tests.support.kuberay import (
    KUBERAY,
    compose,
    deployment_container,
    find,
    head_service_fqdn,
    head_service_name,
    load_manifests,
    secret_values,
    serve_config,
    serve_service_name,
)
from tests.support.paths import REPO
from tests.support.workers import build_tree, free_ports, small_weights, tree_bytes

pytestmark = pytest.mark.slow

BINDIR = Path(sys.executable).parent
#: The resolution of the small networks that stand in for the published ones.
SMALL_NET = {"height": 32, "width": 256}
#: PandaSet's class count, for the small network that stands in for its published one.
PANDA_CLASSES = 15


@dataclass
class Node:
    """A Ray node started from its composed command, in a process group of its own."""

    name: str
    proc: subprocess.Popen
    log: Path

    def kill(self, sig: int = signal.SIGKILL) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, sig)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(10)


@dataclass
class Cluster:
    """The running deployment: nodes, addresses, the Ray token, mounts and the gateway."""

    tmp: Path
    mounts: dict[str, Path]
    dashboard: str
    serve_url: str
    token: str
    env: dict[str, str]
    nodes: list[Node] = field(default_factory=list)
    gateway: Gateway | None = None
    gateway_cmd: list[str] = field(default_factory=list)
    gateway_env: dict[str, str] = field(default_factory=dict)

    def ray_api(self, path: str) -> object:
        """A GET on the dashboard's REST API, with the Ray token."""
        headers = {"Authorization": f"Bearer {self.token}"}
        answer = httpx.get(self.dashboard + path, headers=headers, timeout=30)
        answer.raise_for_status()
        return answer.json()

    def ray_jobs(self) -> dict[str, str]:
        """Status of every Ray job by submission id."""
        return {j["submission_id"]: j["status"] for j in self.ray_api("/api/jobs/")}  # type: ignore[union-attr]

    def running_replicas(self) -> int:
        """Running replicas of the ScanModel deployment."""
        apps = self.ray_api("/api/serve/applications/")["applications"]  # type: ignore[index]
        replicas = apps["rangeret"]["deployments"]["ScanModel"]["replicas"]
        return sum(1 for r in replicas if r["state"] == "RUNNING")

    def client(self, timeout: float = 120) -> httpx.Client:
        """A client of the gateway with the API token of the Deployment's Secret."""
        token = self.gateway_env["RANGERET_API_TOKEN"]
        return httpx.Client(
            base_url=self.gateway.url,
            headers={"Authorization": f"Bearer {token}"},
            timeout=timeout,
        )

    def start_gateway(self) -> Gateway:
        log = self.tmp / "gateway.log"
        with open(log, "ab") as out:
            proc = subprocess.Popen(
                self.gateway_cmd,
                cwd=REPO,
                env=self.gateway_env,
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        gw = Gateway(f"http://127.0.0.1:{self.gateway_env['RANGERET_PORT']}", proc, log)
        self.gateway = wait_healthy(gw, timeout=180)
        return self.gateway


def _mapped(value: str, mounts: dict[str, Path]) -> str:
    """A path in a pod with the volume mounts replaced by the test's folders."""
    for mount, folder in mounts.items():
        if value == mount or value.startswith(mount + "/"):
            return str(folder) + value[len(mount) :]
    return value


def _start(name: str, argv: list[str], env: dict[str, str], tmp: Path) -> Node:
    log = tmp / f"{name}.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen(
            argv, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True
        )
    return Node(name, proc, log)


def _wait(what: str, check, timeout: float, nodes: list[Node] = ()) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if check():
            return
        for node in nodes:
            if node.proc.poll() is not None:
                pytest.fail(f"{node.name} exited: {node.log.read_text()[-3000:]}")
        time.sleep(0.5)
    pytest.fail(f"{what} within {timeout:g} s")


def _cluster_ports(nodes: int, workers: int = 40) -> list[list[int]]:
    """For each node, nine ports and the first of `workers` + 1 worker ports, all free now and
    none shared between nodes (ports are taken together, so no node gets another's)."""
    while True:
        ports = free_ports(10 * nodes)
        chosen = [ports[i * 10 : i * 10 + 10] for i in range(nodes)]
        ranges = [range(c[-1], c[-1] + workers + 1) for c in chosen]
        singles = [p for c in chosen for p in c[:-1]]
        if not any(p in r for r in ranges for p in singles) and not any(
            a is not b and (a.start in b or b.start in a) for a in ranges for b in ranges
        ):
            return chosen


def _node_params(ports: list[int], head: bool) -> tuple[dict[str, object], int, int]:
    """rayStartParams for one node's ports (and the head's temp folder); its GCS and dashboard
    ports."""
    gcs, dash, client, agent, grpc, metrics, nm, om, runtime_env, wmin = ports
    params: dict[str, object] = {
        "dashboard-agent-listen-port": str(agent),
        "dashboard-agent-grpc-port": str(grpc),
        "metrics-export-port": str(metrics),
        "node-manager-port": str(nm),
        "object-manager-port": str(om),
        "runtime-env-agent-port": str(runtime_env),
        "min-worker-port": str(wmin),
        "max-worker-port": str(wmin + 40),
        "object-store-memory": str(400 << 20),
        "disable-usage-stats": "true",
    }
    if head:
        params.update(
            {
                "port": str(gcs),
                "dashboard-host": "127.0.0.1",
                "dashboard-port": str(dash),
                "ray-client-server-port": str(client),
                "temp-dir": f"/tmp/rr-{os.getpid()}-{gcs}",  # Ray's socket paths stay short
            }
        )
    return params, gcs, dash


@pytest.fixture(scope="module")
def cluster(tmp_path_factory) -> Iterator[Cluster]:
    tmp = tmp_path_factory.mktemp("deployment")
    mounts = {
        name: tmp / name.strip("/").replace("/", "-")
        for name in ("/data", "/models", "/results", "/etc/rangeret")
    }
    for folder in mounts.values():
        folder.mkdir()
    shutil.move(small_weights(tmp), mounts["/models"] / "rangeret-kitti-657.pt")
    torch.manual_seed(3)
    panda = build_model("rangeret-cir", 32, 256, num_classes=PANDA_CLASSES, layers=1)
    torch.save(panda.state_dict(), mounts["/models"] / "rangeret-panda-600.pt")
    (config_map,) = load_manifests(KUBERAY / "models.yaml")
    models_file = yaml.safe_load(config_map["data"]["models.yaml"])
    for entry in models_file["models"].values():
        entry["checkpoint"] = _mapped(entry["checkpoint"], mounts)
    (mounts["/etc/rangeret"] / "models.yaml").write_text(yaml.safe_dump(models_file))

    docs = load_manifests(KUBERAY / "rayservice.yaml")
    service = find(docs, "RayService")
    secrets = secret_values(load_manifests(KUBERAY / "secrets.example.yaml"))
    base = {k: v for k, v in os.environ.items() if not k.startswith(("RANGERET_", "RAY_"))}
    base["PATH"] = f"{BINDIR}{os.pathsep}{os.environ['PATH']}"

    ports = _cluster_ports(3)
    params, gcs, dash = _node_params(ports[0], head=True)
    head = compose(
        service, "head", params=params, resources={"cpu": "2", "memory": "4Gi"}, secrets=secrets
    )
    assert "ray start" in head.script and "--head" in head.script and "--block" in head.script
    token = head.env["RAY_AUTH_TOKEN"]
    env = {**base, **head.env}
    nodes = [_start("head", head.argv, env, tmp)]
    dashboard = f"http://127.0.0.1:{dash}"
    made = Cluster(tmp, mounts, dashboard, "", token, env, nodes)
    try:
        _wait("the head's dashboard answered", lambda: _answers(made, "/api/jobs/"), 180, nodes)
        fqdn = head_service_fqdn(service)
        for i in (1, 2):
            params, _, _ = _node_params(ports[i], head=False)
            worker = compose(
                service,
                "gpu",
                params=params,
                resources={"cpu": "2", "memory": "4Gi", "nvidia.com/gpu": "2"},
                addresses={fqdn: f"127.0.0.1:{gcs}"},
                secrets=secrets,
            )
            assert f"--address=127.0.0.1:{gcs}" in worker.script
            nodes.append(_start(f"worker-{i}", worker.argv, {**base, **worker.env}, tmp))
            _wait(f"worker node {i} joined", lambda i=i: _gpus(made) == 2 * i, 180, nodes)

        (serve_port,) = free_ports(1)
        config = serve_config(service)
        config["http_options"] = {"host": "127.0.0.1", "port": serve_port}
        app = config["applications"][0]
        app["args"] = {
            k: _mapped(v, mounts) if isinstance(v, str) else v for k, v in app["args"].items()
        }
        app["args"].update(SMALL_NET)
        deployment = app["deployments"][0]
        deployment["autoscaling_config"].update(
            min_replicas=1, max_replicas=2, upscale_delay_s=1, downscale_delay_s=4
        )
        deployment["ray_actor_options"]["num_cpus"] = 1
        path = tmp / "serve.yaml"
        path.write_text(yaml.safe_dump(config))
        subprocess.run(
            [str(BINDIR / "serve"), "deploy", str(path), "-a", dashboard], env=env, check=True
        )
        made.serve_url = f"http://127.0.0.1:{serve_port}{app['route_prefix']}"
        _wait(
            "the Serve application answered",
            lambda: _answers(made, "/info", made.serve_url, auth=False),
            300,
            nodes,
        )

        (port,) = free_ports(1)
        gateway = deployment_container(
            find(load_manifests(KUBERAY / "gateway.yaml"), "Deployment"),
            secrets=secrets,
            addresses={
                serve_service_name(service): f"127.0.0.1:{serve_port}",
                head_service_name(service): f"127.0.0.1:{dash}",
            },
        )
        assert gateway.args[0] == "gateway"
        net = [f"--{k}={v}" for k, v in SMALL_NET.items()]
        made.gateway_cmd = [
            "bash",
            str(REPO / "deploy" / "entrypoint.sh"),
            *(_mapped(a, mounts) for a in gateway.args),
            *net,
            "--log-level=warning",
        ]
        made.gateway_env = {
            **base,
            **{k: _mapped(v, mounts) for k, v in gateway.env.items()},
            "RANGERET_HOST": "127.0.0.1",
            "RANGERET_PORT": str(port),
        }
        made.start_gateway()
        yield made
    finally:
        if made.gateway is not None:
            made.gateway.stop()
        for node in reversed(made.nodes):
            node.kill(signal.SIGTERM)
        shutil.rmtree(head.params["temp-dir"], ignore_errors=True)


def _answers(cluster: Cluster, path: str, base: str | None = None, auth: bool = True) -> bool:
    headers = {"Authorization": f"Bearer {cluster.token}"} if auth else {}
    try:
        return httpx.get((base or cluster.dashboard) + path, headers=headers, timeout=5).is_success
    except httpx.TransportError:
        return False


def _gpus(cluster: Cluster) -> int:
    """GPUs of the cluster's live nodes."""
    try:
        nodes = cluster.ray_api("/api/v0/nodes?detail=1")["data"]["result"]["result"]  # type: ignore[index]
    except (httpx.HTTPError, KeyError):
        return 0
    return int(sum(n["resources_total"].get("GPU", 0) for n in nodes if n["state"] == "ALIVE"))


def _predict(weights: Path, data: Path, out: Path, sequences: list[str]) -> None:
    """`rangeret predict` of the same weights in this process: the labels to match."""
    argv = ["predict", "-q", "--dataset", str(data), "--out", str(out), "--sequences", *sequences]
    net = ["--checkpoint", str(weights), "--height", "32", "--width", "256", "--device", "cpu"]
    assert rangeret_main([*argv, *net]) == 0


def _evaluate(data: Path, pred: Path, out: Path, sequences: list[str]) -> dict:
    argv = ["evaluate", "-q", "--dataset", str(data), "--predictions", str(pred)]
    assert rangeret_main([*argv, "--sequences", *sequences, "--json", str(out)]) == 0
    return json.loads(out.read_text())


def _same_report(served: dict, reference: dict) -> None:
    for key in ("confusion", "miou", "iou", "per_sequence", "per_distance", "num_scans"):
        assert served[key] == reference[key], key


def test_single_scans_through_serve_equal_rangeret_predict(cluster):
    data = build_tree(cluster.mounts["/data"] / "scans", labelled=2, unlabelled=2)
    weights = cluster.mounts["/models"] / "rangeret-kitti-657.pt"
    _predict(weights, data, cluster.tmp / "scans-pred", ["08", "11"])
    expected = tree_bytes(cluster.tmp / "scans-pred")
    with cluster.client() as client:
        health = client.get("/healthz").json()
        assert health["backend"] == "serve" and health["status"] == "ok", health
        for scan in sorted(data.rglob("*.bin")):
            answer = client.post("/v1/scans", content=scan.read_bytes(), headers=OCTET)
            assert answer.status_code == 200, answer.text
            key = f"sequences/{scan.parent.parent.name}/predictions/{scan.stem}.label"
            assert answer.content == expected[key]


def test_each_model_of_the_one_models_file_labels_as_rangeret_predict(cluster, tmp_path):
    """The ConfigMap's two models through the gateway and the Serve application: a PandaSet scan
    with `?model=panda` and a SemanticKITTI scan with no model (the default, `kitti`), each
    labelled as `rangeret predict` labels it with that model's checkpoint; both listed alike by
    the gateway and the application."""
    panda_root = cluster.mounts["/data"] / "panda"
    profile = load_profile("pandaset").with_overrides(**SMALL_NET)
    simulate_dataset(panda_root, {"1": 1}, seed=4, profile=profile)
    weights = cluster.mounts["/models"] / "rangeret-panda-600.pt"
    argv = ["predict", "-q", "--dataset", str(panda_root), "--out", str(tmp_path / "panda")]
    net = ["--checkpoint", str(weights), "--profile", "pandaset", "--height", "32"]
    assert (
        rangeret_main([*argv, "--sequences", "1", *net, "--width", "256", "--device", "cpu"]) == 0
    )
    (scan,) = sorted(panda_root.rglob("*.bin"))
    expected = prediction_path(tmp_path / "panda", "001", scan.stem)
    kitti = sorted((cluster.mounts["/data"] / "scans").rglob("*.bin"))[0]
    _predict(
        cluster.mounts["/models"] / "rangeret-kitti-657.pt",
        kitti.parents[3],
        tmp_path / "k",
        [kitti.parents[1].name],
    )
    with cluster.client() as client:
        answer = client.post(
            "/v1/scans", params={"model": "panda"}, content=scan.read_bytes(), headers=OCTET
        )
        assert answer.status_code == 200, answer.text
        assert answer.headers["x-rangeret-model"] == "panda"
        assert answer.content == expected.read_bytes()
        default = client.post("/v1/scans", content=kitti.read_bytes(), headers=OCTET)
        assert default.headers["x-rangeret-model"] == "kitti"
        key = f"sequences/{kitti.parents[1].name}/predictions/{kitti.stem}.label"
        assert default.content == tree_bytes(tmp_path / "k")[key]
        listed = client.get("/v1/models").json()
    info = httpx.get(cluster.serve_url + "/info", timeout=10).json()
    assert listed["default"] == info["default"] == "kitti"
    assert [m["id"] for m in listed["models"]] == [m["id"] for m in info["models"]]
    assert [m["profile"] for m in info["models"]] == ["semantickitti", "pandaset"]


def test_the_model_deployment_scales_out_under_load_and_back_in(cluster, capsys):
    body = sorted((cluster.mounts["/data"] / "scans").rglob("*.bin"))[0].read_bytes()
    assert cluster.running_replicas() == 1
    seen: list[int] = []
    stop = threading.Event()

    def watch() -> None:
        while not stop.is_set():
            seen.append(cluster.running_replicas())
            time.sleep(0.5)

    def client_loop() -> None:
        with cluster.client(timeout=300) as client:
            while not stop.is_set():
                assert client.post("/v1/scans", content=body, headers=OCTET).status_code == 200

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    clients = [threading.Thread(target=client_loop, daemon=True) for _ in range(24)]
    for c in clients:
        c.start()
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and max(seen, default=0) < 2:
        time.sleep(0.5)
    stop.set()
    for c in clients:
        c.join(300)
    peak = max(seen)
    _wait("the deployment scaled back in", lambda: cluster.running_replicas() == 1, 120)
    watcher.join(10)
    with capsys.disabled():
        print(f"\nServe replicas observed: 1 at rest, {peak} under 24 clients, 1 after the load")
    assert peak == 2


def _upload(client: httpx.Client, root: Path) -> str:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for path in sorted(root.rglob("*")):
            if path.is_file():
                zf.write(path, path.relative_to(root).as_posix())
    answer = client.post(
        "/v1/jobs", files={"archive": ("data.zip", buf.getvalue(), "application/zip")}
    )
    assert answer.status_code == 202, answer.text
    return answer.json()["id"]


def _predictions_folder(cluster: Cluster, job_id: str) -> Path:
    return Path(cluster.gateway_env["RANGERET_STATE_DIR"]) / "jobs" / job_id / "predictions"


def test_a_dataset_job_runs_on_while_the_gateway_is_killed(cluster, tmp_path):
    """A dataset job on the data volume: the gateway is SIGKILLed mid-job, its Ray job runs on
    to the end, and the restarted gateway reports it finished with every scan, its report
    equal to `rangeret evaluate`'s; no second Ray job was submitted."""
    data = build_tree(cluster.mounts["/data"] / "long", labelled=12, unlabelled=12)
    weights = cluster.mounts["/models"] / "rangeret-kitti-657.pt"
    with cluster.client() as client:
        answer = client.post("/v1/jobs", json={"dataset": str(data), "sequences": ["08", "11"]})
        assert answer.status_code == 202, answer.text
        job_id = answer.json()["id"]
        _wait(
            "the job wrote a prediction",
            lambda: any(_predictions_folder(cluster, job_id).rglob("*.label")),
            300,
        )
    cluster.gateway.stop(signal.SIGKILL)
    ray_job = f"{job_id}-1"
    assert cluster.ray_jobs()[ray_job] in ("PENDING", "RUNNING", "SUCCEEDED")
    _wait(
        "the Ray job finished without the gateway",
        lambda: cluster.ray_jobs()[ray_job] == "SUCCEEDED",
        300,
    )
    cluster.start_gateway()
    with cluster.client() as client:
        status = wait_job(client, job_id, timeout=300)
        assert status["state"] == "succeeded", status
        assert (status["total"], status["done"], status["failed"]) == (24, 24, 0)
        report = client.get(f"/v1/jobs/{job_id}/report").json()
    assert [k for k in cluster.ray_jobs() if k.startswith(job_id)] == [ray_job]
    _predict(weights, data, tmp_path / "pred", ["08", "11"])
    assert tree_bytes(_predictions_folder(cluster, job_id)) == tree_bytes(tmp_path / "pred")
    _same_report(report, _evaluate(data, tmp_path / "pred", tmp_path / "eval.json", ["08"]))


def test_an_archive_job_loses_no_scan_when_a_worker_node_is_killed(cluster, tmp_path):
    """An uploaded archive of two test sequences (unpacked on the results volume): a worker node
    holding one of the job's model actors is SIGKILLed mid-job; every scan is predicted once or
    named as a failure, and the job's archive passes the submission validator."""
    data = tmp_path / "data"
    for sequence in ("11", "12"):
        build_tree(data, labelled=0, unlabelled=20, seq_test=sequence)
    weights = cluster.mounts["/models"] / "rangeret-kitti-657.pt"
    _predict(weights, data, tmp_path / "pred", ["11", "12"])
    killed: list[int] = []
    with cluster.client() as client:
        job_id = _upload(client, data)
        out = _predictions_folder(cluster, job_id)
        _wait("the job wrote a prediction", lambda: any(out.rglob("*.label")), 300)
        killed.append(len(list(out.rglob("*.label"))))
        victim = _node_of_a_model_actor(cluster)
        victim.kill()
        status = wait_job(client, job_id, timeout=600)
        zipped = client.get(f"/v1/jobs/{job_id}/predictions")
    assert killed[0] < 40, "the node was killed after the job, not during it"
    written = tree_bytes(out)
    failures = {e.split(":")[0] for e in status["errors"]}
    assert status["total"] == 40 and status["done"] + status["failed"] == 40, status
    expected = tree_bytes(tmp_path / "pred")
    for key, labels in expected.items():
        scan = "/".join((key.split("/")[1], key.rsplit("/", 1)[1].removesuffix(".label")))
        assert written.get(key) == labels or scan in failures, key
    assert set(written) <= set(expected)
    assert status["state"] == "succeeded", status
    (tmp_path / "archive.zip").write_bytes(zipped.content)
    check = validate_submission(
        tmp_path / "archive.zip", data, allow_partial=True, labels=semantickitti()
    )
    assert check.ok and check.scans == 40, check


def _ancestors(pid: int) -> set[int]:
    """A process's parent, its parent's parent, and so on."""
    found: set[int] = set()
    while pid > 1 and pid not in found:
        found.add(pid)
        try:
            stat = Path(f"/proc/{pid}/stat").read_text()
        except OSError:
            break
        pid = int(stat.rsplit(")", 1)[1].split()[1])
    return found


def _node_of_a_model_actor(cluster: Cluster) -> Node:
    """The worker node that runs one of the job's model actors (by its process group)."""
    deadline = time.monotonic() + 60
    actors: list[dict] = []
    while time.monotonic() < deadline:
        actors = cluster.ray_api("/api/v0/actors?detail=1&limit=1000")["data"]["result"]["result"]  # type: ignore[index]
        for actor in actors:
            if "ModelWorker" in actor.get("class_name", "") and actor["state"] == "ALIVE":
                ancestors = _ancestors(actor.get("pid") or 0)
                for node in cluster.nodes[1:]:
                    if node.proc.pid in ancestors:
                        return node
        time.sleep(0.2)
    names = sorted({(a.get("class_name"), a["state"]) for a in actors})
    pytest.fail(f"no model actor of the job was found on a worker node: {names}")
