"""Deployment files: the KubeRay manifests validate strictly against KubeRay's CRD schemas, their
Ray containers start as KubeRay composes them, the pieces name each other consistently; the image,
its entrypoint and the cluster launcher config fit; and the README's `ray job submit` recipe runs
as written."""

from __future__ import annotations

import copy
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from rangeret.dataset.labels import semantickitti
from rangeret.inference.model_set import ModelSet
from rangeret.models.weights.hub import file_sha256
from rangeret.submission.archives import validate_submission
from tests.support.kuberay import (
    KUSTOMIZATION,
    ManifestError,
    admits,
    cluster_spec,
    compose,
    deployment_container,
    find,
    head_address,
    head_ports,
    head_service_name,
    load_manifests,
    ray_groups,
    secret_values,
    serve_config,
    serve_config_problems,
    serve_service_name,
    validate,
)
from tests.support.paths import REPO
from tests.support.workers import small_weights
from workers.predict_job import build_parser as job_parser

DEPLOY = REPO / "deploy"
KUBERAY = DEPLOY / "kuberay"
RAY_KINDS = ("RayCluster", "RayJob", "RayService")
#: The label the manifests give every Ray pod, for the NetworkPolicy.
RAY_POD_LABEL = {"app.kubernetes.io/name": "rangeret-ray"}


def _docs(path: Path) -> list[dict]:
    return load_manifests(path)


def _manifest_paths() -> list[Path]:
    """Every manifest under deploy/kuberay, its folders included; kustomization.yaml files are
    not manifests (kustomize reads them)."""
    return sorted(p for p in KUBERAY.rglob("*.yaml") if p.name != KUSTOMIZATION)


def _all_docs() -> list[tuple[str, dict]]:
    """(path under deploy/kuberay, document) of every manifest."""
    return [(p.relative_to(KUBERAY).as_posix(), d) for p in _manifest_paths() for d in _docs(p)]


def _ray_docs() -> list[tuple[str, dict]]:
    return [(name, d) for name, d in _all_docs() if d["kind"] in RAY_KINDS]


def _service() -> dict:
    return find(_docs(KUBERAY / "rayservice.yaml"), "RayService")


def _job() -> dict:
    return find(_docs(KUBERAY / "test-set" / "rayjob.yaml"), "RayJob")


def _gateway() -> dict:
    return find(_docs(KUBERAY / "gateway.yaml"), "Deployment")


def _models_file() -> tuple[str, dict]:
    """The ConfigMap that holds the models file: its name, and the file's mapping."""
    (config_map,) = _docs(KUBERAY / "models.yaml")
    return config_map["metadata"]["name"], yaml.safe_load(config_map["data"]["models.yaml"])


def _secrets() -> dict[str, dict[str, str]]:
    return secret_values(_docs(KUBERAY / "secrets.example.yaml"))


def _walk(value: object, path: tuple = ()):
    """(path, node) of every mapping, list and scalar in a parsed manifest, depth first."""
    yield path, value
    if isinstance(value, dict):
        for key, item in value.items():
            yield from _walk(item, (*path, key))
    elif isinstance(value, list):
        for i, item in enumerate(value):
            yield from _walk(item, (*path, i))


def _get(value: object, path: tuple) -> object:
    for part in path:
        value = value[part]  # type: ignore[index]
    return value


def _ray_pod_templates(doc: dict) -> list[tuple[str, dict]]:
    """(group name, pod spec) of every Ray pod a manifest defines: a RayCluster's, a RayJob's
    rayClusterSpec and a RayService's rayClusterConfig, head and worker groups."""
    if doc["kind"] not in RAY_KINDS:
        return []
    cluster = cluster_spec(doc)
    groups = [("head", cluster["headGroupSpec"])]
    groups += [(g["groupName"], g) for g in cluster.get("workerGroupSpecs", [])]
    return [(name, group["template"]["spec"]) for name, group in groups]


def _pod_labels(doc: dict) -> list[dict]:
    """The labels of every Ray pod template of a manifest."""
    cluster = cluster_spec(doc)
    groups = [cluster["headGroupSpec"], *cluster.get("workerGroupSpecs", [])]
    return [(g["template"].get("metadata") or {}).get("labels") or {} for g in groups]


# --- the manifests as Kubernetes reads them ---------------------------------------------------


def test_kuberay_manifests_parse_and_fit_together():
    kinds = {
        p.relative_to(KUBERAY).as_posix(): [d["kind"] for d in _docs(p)] for p in _manifest_paths()
    }
    assert kinds == {
        "fill-volumes/job.yaml": ["Job"],
        "gateway.yaml": ["Deployment", "Service"],
        "models.yaml": ["ConfigMap"],
        "networkpolicy.yaml": ["NetworkPolicy"],
        "test-set/rayjob.yaml": ["RayJob"],
        "rayservice.yaml": ["RayService"],
        "secrets.example.yaml": ["Secret", "Secret"],
        "storage.yaml": ["PersistentVolumeClaim"] * 3,
    }
    claims = {d["metadata"]["name"] for d in _docs(KUBERAY / "storage.yaml")}
    secrets = _secrets()
    referenced = 0
    for name, doc in _all_docs():
        for path, node in _walk(doc):
            if path[-1:] == ("persistentVolumeClaim",):
                assert node["claimName"] in claims, (name, path)
                referenced += 1
            if path[-1:] == ("secretKeyRef",):
                assert node["key"] in secrets.get(node["name"], {}), (name, path, node)
                referenced += 1
    assert referenced >= 3 * 4 + 3
    for name, doc in _ray_docs():
        auth = cluster_spec(doc)["authOptions"]
        assert auth["mode"] == "token", name
        assert "auth_token" in secrets[auth["secretName"]], name
    # The Service reaches the gateway's pods on a port their container names.
    service = find(_docs(KUBERAY / "gateway.yaml"), "Service")
    pod = _gateway()["spec"]["template"]
    assert service["spec"]["selector"].items() <= pod["metadata"]["labels"].items()
    names = {p["name"] for c in pod["spec"]["containers"] for p in c.get("ports", [])}
    assert {p["targetPort"] for p in service["spec"]["ports"]} <= names


def test_every_manifest_validates_strictly_against_its_schema():
    for name, doc in _all_docs():
        assert validate(doc) == [], f"{name} {doc['kind']}"


def test_the_validator_refuses_broken_copies_of_every_manifest():
    """Each mapping of each manifest given an unknown field, and each scalar replaced by a
    mapping (a wrong type wherever a scalar belongs), is refused; so are a few real slips."""
    bogus = {"bogus": True}
    for name, doc in _all_docs():
        tried = 0
        for path, node in _walk(doc):
            broken = copy.deepcopy(doc)
            if isinstance(node, dict):
                _get(broken, path)["bogusField"] = bogus  # type: ignore[index]
            elif isinstance(node, list):
                continue
            else:
                _get(broken, path[:-1])[path[-1]] = bogus  # type: ignore[index]
            assert validate(broken), f"{name}: {'.'.join(map(str, path))} broken, yet accepted"
            tried += 1
        assert tried > 5, name

    # The Serve config inside the RayService's string: every mapping and scalar but the
    # builder's args and the runtime_env, which are free-form for Serve (test_the_serve_application
    # checks them).
    service = _service()
    config = serve_config(service)
    tried = 0
    for path, node in _walk(config):
        if "args" in path or "runtime_env" in path or isinstance(node, list):
            continue
        broken = copy.deepcopy(config)
        if isinstance(node, dict):
            _get(broken, path)["bogusField"] = 1  # type: ignore[index]
        else:
            _get(broken, path[:-1])[path[-1]] = bogus  # type: ignore[index]
        copied = copy.deepcopy(service)
        copied["spec"]["serveConfigV2"] = yaml.safe_dump(broken)
        assert validate(copied), f"serveConfigV2 {'.'.join(map(str, path))} broken, yet accepted"
        tried += 1
    assert tried > 10

    def refused(doc: dict, path: tuple, value: object) -> list[str]:
        broken = copy.deepcopy(doc)
        _get(broken, path[:-1])[path[-1]] = value  # type: ignore[index]
        return validate(broken)

    head = ("spec", "rayClusterConfig", "headGroupSpec")
    container = (*head, "template", "spec", "containers", 0)
    assert refused(service, (*head, "rayStartParams", "num-gpus"), 0)  # must be a string
    assert refused(service, (*container, "resources", "limits", "memory"), "16 GiB")
    assert refused(service, (*container, "ports", 0, "containerPort"), "6379")
    assert refused(service, ("spec", "rayClusterConfig", "authOptions", "mode"), "Token")
    assert refused(service, ("spec", "rayClusterConfig", "rayVersion"), 2.6)
    assert refused(service, ("spec", "serveConfigV2"), "applications: [{name: x}]")
    assert refused(service, ("spec", "serveConfigV2"), "applications: [\n")
    assert refused(_job(), ("spec", "shutdownAfterJobFinishes"), "true")
    assert refused(_gateway(), ("spec", "replicas"), "1")
    assert refused(_gateway(), ("spec", "strategy", "type"), "recreate")
    assert refused(_gateway(), ("metadata", "name"), "Rangeret_Gateway")
    with pytest.raises(ManifestError, match="given twice"):
        load_manifests("a: 1\nb: {c: 2, c: 3}\n")
    # The Serve config's own wrong types and unknown keys, which Serve would ignore.
    text = service["spec"]["serveConfigV2"]
    assert serve_config_problems(text) == []
    assert serve_config_problems(
        text.replace("max_ongoing_requests: 16", "max_ongoing_requests: x")
    )
    assert serve_config_problems(text.replace("max_queued_requests", "max_queue_requests"))
    assert serve_config_problems(text.replace("min_replicas: 1", "min_replica: 1"))


# --- how KubeRay starts the Ray containers ----------------------------------------------------


def test_kuberay_starts_every_ray_container_with_its_own_ray_start(tmp_path):
    """The composed command of each Ray container: the head runs `ray start --head ... --block`,
    workers join the head service; nothing before it that could fail; every flag one Ray's
    `ray start` takes; and the script, run by bash, calls `ray start` with exactly those."""
    from ray.scripts.scripts import start

    stub = tmp_path / "bin" / "ray"
    stub.parent.mkdir()
    stub.write_text('#!/bin/sh\nprintf "%s\\n" "$@" > "$RAY_ARGS"\n')
    stub.chmod(0o755)
    secrets = _secrets()
    checked = []
    for name, doc in _ray_docs():
        for group in ray_groups(doc):
            node = compose(doc, group, secrets=secrets)
            where = f"{name} {group}"
            assert node.rewritten and node.command == ["/bin/bash", "-c", "--"], where
            assert node.cmd.strip() == "" or _exits_0_in_bash(node.cmd, tmp_path), where
            argv = shlex.split(node.ray_start)
            assert argv[:2] == ["ray", "start"] and "--block" in argv, where
            start.make_context("ray start", argv[2:])  # refuses an option Ray does not have
            if node.head:
                assert "--head" in argv and "--num-gpus=0" in argv, where
                assert "--dashboard-host=0.0.0.0" in argv, where
                assert not any(a.startswith("--address") for a in argv), where
            else:
                assert f"--address={head_address(doc)}" in argv, where
                assert "--num-gpus=1" in argv and "--head" not in argv, where
                assert (
                    head_address(doc) == f"{head_service_name(doc)}.default.svc.cluster.local:6379"
                )
            recorded = tmp_path / f"{group}.args"
            run = subprocess.run(
                node.argv,
                env={"PATH": f"{stub.parent}:/usr/bin:/bin", "RAY_ARGS": str(recorded), **node.env},
                cwd=tmp_path,
                capture_output=True,
                text=True,
                timeout=30,
                check=False,
            )
            assert run.returncode == 0, (where, run.stderr)
            assert recorded.read_text().splitlines() == argv[1:], where
            checked.append(where)
    assert checked == [
        "rayservice.yaml head",
        "rayservice.yaml gpu",
        "test-set/rayjob.yaml head",
        "test-set/rayjob.yaml gpu",
    ]


def _exits_0_in_bash(cmd: str, folder: Path) -> bool:
    """Whether a command KubeRay puts before `ray start` exits 0 under bash, run in an empty
    folder with nothing but the system's PATH."""
    run = subprocess.run(
        ["/bin/bash", "-c", cmd],
        env={"PATH": "/usr/bin:/bin", "HOME": str(folder)},
        cwd=folder,
        capture_output=True,
        timeout=30,
        check=False,
    )
    return run.returncode == 0


def test_the_composition_follows_kuberays_rule():
    """The rule itself, on variants of the RayService: the old `args: ["ray-head"]` fails, a
    command containing `ray start` or the overwrite annotation is left alone, flags are sorted
    with true/false handled, resources give the counts, and the caller's replacements apply."""
    service = _service()
    secrets = _secrets()
    container = ("spec", "rayClusterConfig", "headGroupSpec", "template", "spec", "containers", 0)

    old = copy.deepcopy(service)
    _get(old, container)["args"] = ["ray-head"]
    head = compose(old, "head", secrets=secrets)
    assert head.script.startswith(" ray-head  && ulimit -n ${RAY_START_ULIMIT_OPEN_FILES:-65536}; ")
    assert not _exits_0_in_bash(head.cmd, Path("/tmp"))  # exit 127: what the old manifest ran

    kept = copy.deepcopy(service)
    _get(kept, container)["command"] = ["bash", "-c", "ray start --head --block"]
    assert not compose(kept, "head", secrets=secrets).rewritten
    annotated = copy.deepcopy(service)
    annotated["spec"]["rayClusterConfig"]["headGroupSpec"]["template"]["metadata"][
        "annotations"
    ] = {"ray.io/overwrite-container-cmd": "true"}
    _get(annotated, container)["command"] = ["sleep", "infinity"]
    assert compose(annotated, "head", secrets=secrets).argv == ["sleep", "infinity"]

    worker = compose(
        service,
        "gpu",
        params={"include-dashboard": "false", "disable-usage-stats": True, "num-gpus": None,
                "temp-dir": "/tmp/x", "verbose": "false"},
        resources={"cpu": "1500m", "memory": "2Gi", "nvidia.com/gpu": "0"},
        addresses={f"{head_service_name(service)}.default.svc.cluster.local": "127.0.0.1:16379"},
        secrets=secrets,
    )  # fmt: skip
    assert worker.ray_start == (
        "ray start  --address=127.0.0.1:16379  --block  --dashboard-agent-listen-port=52365 "
        " --disable-usage-stats  --include-dashboard=false  --memory=2147483648 "
        " --metrics-export-port=8080  --num-cpus=2  --temp-dir=/tmp/x "
    )
    assert worker.env == {
        "RAY_AUTH_MODE": "token",
        "RAY_AUTH_TOKEN": secrets["rangeret-ray-token"]["auth_token"],
    }


def test_the_head_lists_the_ports_its_services_expose():
    service_ports = head_ports(_service())
    assert {"gcs": 6379, "dashboard": 8265, "serve": 8000}.items() <= service_ports.items()
    assert {"gcs": 6379, "dashboard": 8265}.items() <= head_ports(_job()).items()
    assert "client" not in service_ports and 10001 not in service_ports.values()  # no Ray Client


def test_ray_token_authentication_is_configured_in_one_place():
    """authOptions on both clusters; no Ray container sets the token by hand; KubeRay gives each
    the token of the Secret; the gateway reads the same Secret and key."""
    secrets = _secrets()
    token = secrets["rangeret-ray-token"]["auth_token"]
    for name, doc in _ray_docs():
        assert cluster_spec(doc)["authOptions"] == {
            "mode": "token",
            "secretName": "rangeret-ray-token",
        }
        for group, pod in _ray_pod_templates(doc):
            for container in pod["containers"]:
                assert not {e["name"] for e in container.get("env", [])} & {
                    "RAY_AUTH_MODE", "RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH"
                }, f"{name} {group}"  # fmt: skip
            env = compose(doc, group, secrets=secrets).env
            assert env["RAY_AUTH_MODE"] == "token" and env["RAY_AUTH_TOKEN"] == token
    assert "submitterPodTemplate" not in _job()["spec"]  # the operator gives the token itself
    gateway = {e["name"]: e for e in _gateway()["spec"]["template"]["spec"]["containers"][0]["env"]}
    assert gateway["RAY_AUTH_MODE"]["value"] == "token"
    assert gateway["RAY_AUTH_TOKEN"]["valueFrom"]["secretKeyRef"] == {
        "name": "rangeret-ray-token",
        "key": "auth_token",
    }
    assert gateway["RANGERET_API_TOKEN"]["valueFrom"]["secretKeyRef"] == {
        "name": "rangeret-tokens",
        "key": "api-token",
    }
    assert deployment_container(_gateway(), secrets=secrets).env["RAY_AUTH_TOKEN"] == token


def test_the_serve_application():
    """The RayService's Serve config: the application, route and deployment the gateway and
    workers.serve_app agree on, GPUs per replica, autoscaling within the GPU group, and builder
    args that are network options the command line takes."""
    from rangeret.inference.spec import InferenceSpec

    service = _service()
    config = serve_config(service)
    assert config["http_options"] == {"host": "0.0.0.0", "port": head_ports(service)["serve"]}
    (app,) = config["applications"]
    assert (app["name"], app["route_prefix"], app["import_path"]) == (
        "rangeret",
        "/rangeret",
        "workers.serve_app:build_app",
    )
    (deployment,) = app["deployments"]
    assert deployment["name"] == "ScanModel"
    assert deployment["ray_actor_options"]["num_gpus"] == 1
    assert 0 < deployment["max_ongoing_requests"] < deployment["max_queued_requests"]
    assert deployment["health_check_timeout_s"] >= deployment["health_check_period_s"] > 0
    scaling = deployment["autoscaling_config"]
    (gpu_group,) = cluster_spec(service)["workerGroupSpecs"]
    assert 1 <= scaling["min_replicas"] <= scaling["max_replicas"] < gpu_group["maxReplicas"]
    assert gpu_group["minReplicas"] == 0 and gpu_group["maxReplicas"] == 8
    assert cluster_spec(service)["enableInTreeAutoscaling"] is True
    assert cluster_spec(service)["rayVersion"] == "2.60.0"

    args = dict(app["args"])
    assert args.pop("batch_wait_ms") >= 0
    assert args.pop("models") == "/etc/rangeret/models.yaml"
    _, models_file = _models_file()
    assert 1 <= args.pop("max_num_models_per_replica") <= len(models_file["models"])
    spec = InferenceSpec.from_mapping(args)
    assert spec.batch_size == args["batch_size"] and spec.to_mapping() == args
    models = ModelSet.from_mapping(models_file, spec)
    assert models.default == "kitti" and len(models) == 2
    assert all(model.checkpoint.startswith("/models/") for _, model in models)
    assert set(app["runtime_env"]) == {"env_vars"}
    assert list(app["runtime_env"]["env_vars"]) == ["RANGERET_MODELS_REVISION"]


def test_the_serve_application_builds_from_the_rayservices_arguments(tmp_path):
    """The import path names the builder, and the RayService's arguments build the application
    from the ConfigMap's models file (its checkpoints read for their SHA-256 and profile, one GPU
    per replica on `device: cuda`)."""
    import importlib

    import torch

    from rangeret.models import build_model

    app = serve_config(_service())["applications"][0]
    module, _, name = app["import_path"].partition(":")
    builder = getattr(importlib.import_module(module), name)
    _, models_file = _models_file()
    models = tmp_path / "models"
    models.mkdir()
    kitti = small_weights(tmp_path).rename(models / "rangeret-kitti-657.pt")
    panda = build_model("rangeret-cir", 32, 256, num_classes=15, layers=1)
    torch.save(panda.state_dict(), models / "rangeret-panda-600.pt")
    text = yaml.safe_dump(models_file).replace("/models/", f"{models}/")
    (tmp_path / "models.yaml").write_text(text)
    args = {**app["args"], "models": str(tmp_path / "models.yaml"), "device": "cuda"}
    built = builder({**args, "height": 32, "width": 256})._bound_deployment
    assert built.name == app["deployments"][0]["name"]
    assert built.ray_actor_options["num_gpus"] == 1
    _, described, per_replica = built.init_args
    assert described["kitti"]["checkpoint_sha256"] == file_sha256(kitti)
    assert {m: d["profile"] for m, d in described.items()} == {
        "kitti": "semantickitti",
        "panda": "pandaset",
    }
    assert per_replica == app["args"]["max_num_models_per_replica"]


def test_the_gateway_reaches_the_rayservice(monkeypatch):
    """The gateway's environment names KubeRay's services of the RayService (Serve proxy and
    route prefix; the dashboard's Jobs API), the results volume the Ray pods mount for its state,
    and only settings that exist; one gateway at a time."""
    from service.settings import Settings

    service = _service()
    deployment = _gateway()
    assert deployment["spec"]["strategy"] == {"type": "Recreate"}
    assert deployment["spec"]["replicas"] == 1
    assert deployment["spec"]["template"]["metadata"]["labels"] == {"app": "rangeret-gateway"}
    gateway = deployment_container(deployment, secrets=_secrets())
    ports, route = head_ports(service), serve_config(service)["applications"][0]["route_prefix"]
    assert gateway.env["RANGERET_SERVE_URL"] == (
        f"http://{serve_service_name(service)}:{ports['serve']}{route}"
    )
    assert gateway.env["RANGERET_JOBS_ADDRESS"] == (
        f"http://{head_service_name(service)}:{ports['dashboard']}"
    )
    assert float(gateway.env["RANGERET_SERVE_TIMEOUT_S"]) > 0
    assert not {"RANGERET_RAY_ADDRESS", "RANGERET_ACTORS"} & set(gateway.env)
    assert gateway.env["RANGERET_DATA_ROOTS"] == "/data"
    # The state folder is on the results claim, mounted at the same path on every Ray pod.
    state = Path(gateway.env["RANGERET_STATE_DIR"])
    pod = deployment["spec"]["template"]["spec"]
    claims = {
        v["name"]: v["persistentVolumeClaim"]["claimName"]
        for v in pod["volumes"]
        if "persistentVolumeClaim" in v
    }
    (mount,) = [
        m for m in pod["containers"][0]["volumeMounts"] if state.is_relative_to(m["mountPath"])
    ]
    assert not mount.get("readOnly")
    for name, doc in _ray_docs():
        for group, ray_pod in _ray_pod_templates(doc):
            ray_claims = {
                v["name"]: v["persistentVolumeClaim"]["claimName"]
                for v in ray_pod["volumes"]
                if "persistentVolumeClaim" in v
            }
            (same,) = [
                m for m in ray_pod["containers"][0]["volumeMounts"]
                if m["mountPath"] == mount["mountPath"]
            ]  # fmt: skip
            assert ray_claims[same["name"]] == claims[mount["name"]], f"{name} {group}"
            assert not same.get("readOnly"), f"{name} {group}"
    for key, value in gateway.env.items():
        monkeypatch.setenv(key, value)
    settings = Settings()
    assert settings.serve_url == "http://rangeret-serve-svc:8000/rangeret"
    assert settings.jobs_address == "http://rangeret-head-svc:8265"
    assert settings.state_dir == Path("/results/gateway") and settings.token


def test_gateway_manifest_names_the_serve_command_and_settings():
    """The gateway's args parse with `rangeret serve`'s parser, name the Serve application's
    network options, and its RANGERET_* variables are settings that exist."""
    from rangeret.cli.main import build_parser
    from rangeret.inference.spec import InferenceSpec
    from service.settings import Settings

    container = _gateway()["spec"]["template"]["spec"]["containers"][0]
    assert container["args"][0] == "gateway" and "command" not in container
    args = build_parser("serve").parse_args(["serve", *container["args"][1:]])
    assert args.checkpoint is None and args.model is None  # the models file names them
    served = dict(serve_config(_service())["applications"][0]["args"])
    env = {e["name"]: e.get("value") for e in container["env"]}
    assert env["RANGERET_MODELS"] == served.pop("models")
    for name in ("batch_wait_ms", "max_num_models_per_replica"):
        served.pop(name)
    values = InferenceSpec.from_args(args).to_mapping()
    assert {k: values.get(k) for k in served} == served
    _, models_file = _models_file()
    job = job_parser().parse_args(shlex.split(_job()["spec"]["entrypoint"])[3:])
    default = models_file["models"][models_file["default"]]
    assert str(job.checkpoint) == default["checkpoint"]
    fields = {f"RANGERET_{name.upper()}" for name in Settings.model_fields}
    for env in container["env"]:
        if env["name"].startswith("RANGERET_"):
            assert env["name"] in fields, env["name"]


def test_the_network_policy_admits_only_the_gateway_to_serve():
    """Serve's port on every Ray pod admits the gateway's pods and other Ray pods, no one else;
    Ray pods reach each other on every port; the dashboard stays reachable for everyone."""
    policies = _docs(KUBERAY / "networkpolicy.yaml")
    (policy,) = policies
    assert policy["spec"]["podSelector"] == {"matchLabels": RAY_POD_LABEL}
    gateway = _gateway()["spec"]["template"]["metadata"]["labels"]
    other = {"app": "something-else"}
    ray_pods = [labels for _, doc in _ray_docs() for labels in _pod_labels(doc)]
    assert len(ray_pods) == 4
    for target in ray_pods:
        assert RAY_POD_LABEL.items() <= target.items()
        assert admits(policies, source=gateway, target=target, port=8000)
        assert not admits(policies, source=other, target=target, port=8000)
        assert not admits(policies, source=None, target=target, port=8000)
        for port in (6379, 8000, 8080, 8265, 10002, 52365):
            assert admits(policies, source=ray_pods[0], target=target, port=port)
        for source in (gateway, other, None):
            assert admits(policies, source=source, target=target, port=8265)
        assert not admits(policies, source=gateway, target=target, port=6379)
    # The policy does not touch the gateway's own pods.
    assert admits(policies, source=other, target=gateway, port=8000)


def test_the_rayjob_brings_its_own_cluster_and_cleans_up():
    spec = _job()["spec"]
    assert "clusterSelector" not in spec and spec["rayClusterSpec"]["workerGroupSpecs"]
    assert spec["shutdownAfterJobFinishes"] is True and spec["ttlSecondsAfterFinished"] > 0
    assert spec["rayClusterSpec"]["rayVersion"] == "2.60.0"


def test_rayjob_entrypoint_names_a_module_and_flags_that_exist():
    argv = shlex.split(_job()["spec"]["entrypoint"])
    assert argv[:3] == ["python", "-m", "workers.predict_job"]
    args = job_parser().parse_args(argv[3:])
    assert args.split == "test" and str(args.submission).endswith(".zip")
    assert str(args.out).startswith("/results") and str(args.dataset).startswith("/data")
    assert str(args.checkpoint) == "/models/rangeret-kitti-657.pt" and args.batch_size == 8


def test_every_ray_container_mounts_data_models_and_results():
    for name, doc in _ray_docs():
        for group, pod in _ray_pod_templates(doc):
            claims = {
                v["name"]: v["persistentVolumeClaim"]
                for v in pod["volumes"]
                if "persistentVolumeClaim" in v
            }
            for container in pod["containers"]:
                mounts = {m["mountPath"]: m for m in container["volumeMounts"]}
                for path, claim, read_only in (
                    ("/data", "rangeret-data", True),
                    ("/models", "rangeret-models", True),
                    ("/results", "rangeret-results", False),
                ):
                    where = f"{name} {group} {container['name']} {path}"
                    assert claims[mounts[path]["name"]]["claimName"] == claim, where
                    assert bool(mounts[path].get("readOnly")) is read_only, where
                assert "command" not in container and "args" not in container


def test_the_gateway_and_every_serving_ray_pod_mount_the_one_models_file():
    """The ConfigMap's file is mounted read-only where the gateway's RANGERET_MODELS and the
    Serve application's `models` argument name it, in the gateway's pod and every RayService pod
    (the application is built on any of them)."""
    name, _ = _models_file()
    path = Path(serve_config(_service())["applications"][0]["args"]["models"])
    pods = [("gateway", _gateway()["spec"]["template"]["spec"])]
    pods += [(group, pod) for group, pod in _ray_pod_templates(_service())]
    for group, pod in pods:
        volumes = {v["name"]: v for v in pod["volumes"]}
        (mount,) = [
            m for m in pod["containers"][0]["volumeMounts"] if m["mountPath"] == str(path.parent)
        ]
        assert volumes[mount["name"]]["configMap"] == {"name": name}, group
        assert mount.get("readOnly") is True, group


# --- the image ----------------------------------------------------------------------------


def test_the_entrypoint_modes(tmp_path):
    """`gateway` (the default) runs `rangeret serve` on 0.0.0.0:8000 with the options given;
    `ray-head` and `ray-worker` are blocking `ray start` commands of their own (plain docker);
    anything else runs as a command."""
    bindir = tmp_path / "bin"
    bindir.mkdir()
    for tool in ("rangeret", "ray"):
        (bindir / tool).write_text(f'#!/bin/sh\nprintf "%s\\n" {tool} "$@" > "$RECORD"\n')
        (bindir / tool).chmod(0o755)

    def run(*args: str) -> list[str]:
        record = tmp_path / "record"
        record.unlink(missing_ok=True)
        subprocess.run(
            [str(DEPLOY / "entrypoint.sh"), *args],
            env={"PATH": f"{bindir}:/usr/bin:/bin", "RECORD": str(record)},
            check=True,
            timeout=30,
        )
        return record.read_text().splitlines()

    gateway = ["rangeret", "serve", "--host", "0.0.0.0", "--port", "8000"]
    assert run() == gateway
    assert run("gateway", "--checkpoint", "/models/x.pt") == [
        *gateway,
        "--checkpoint",
        "/models/x.pt",
    ]
    head = run("ray-head")
    assert head[:3] == ["ray", "start", "--head"] and "--block" in head
    worker = run("ray-worker", "--address", "10.0.0.10:6379")
    assert worker[:2] == ["ray", "start"] and "--block" in worker and "--head" not in worker
    assert run("ray", "job", "list") == ["ray", "job", "list"]


# --- shared memory ------------------------------------------------------------------------


# Ray's object store defaults to this share of a node's memory, and lives in /dev/shm.
OBJECT_STORE_SHARE = 0.3
# Ray caps its default object store at 95 % of /dev/shm, but not below this many bytes
# (ray_constants.REQUIRE_SHM_SIZE_THRESHOLD); past it, a store that does not fit goes to /tmp.
RAY_SHM_THRESHOLD = 10**10

_UNITS = {"": 1, "k": 10**3, "M": 10**6, "G": 10**9, "T": 10**12}
_UNITS.update({"Ki": 2**10, "Mi": 2**20, "Gi": 2**30, "Ti": 2**40})


def _quantity(text: str) -> int:
    """Bytes in a Kubernetes quantity: 5Gi, 512Mi, 10G, 1000."""
    number, unit = re.fullmatch(r"(\d+(?:\.\d+)?)([kMGT]i?)?", str(text)).groups()
    return int(float(number) * _UNITS[unit or ""])


def _docker_size(text: str) -> int:
    """Bytes in a `docker run --shm-size` value: 12g, 512m, 1024 (units are binary)."""
    number, unit = re.fullmatch(r"(\d+)([bkmg]?)", text.lower()).groups()
    return int(number) * {"": 1, "b": 1, "k": 2**10, "m": 2**20, "g": 2**30}[unit]


def test_every_ray_container_mounts_a_memory_backed_dev_shm_for_the_object_store():
    checked = []
    for path in _manifest_paths():
        for doc in _docs(path):
            if doc["kind"] == "RayJob":
                assert doc["spec"].get("clusterSelector") or doc["spec"].get("rayClusterSpec")
            for group, pod in _ray_pod_templates(doc):
                volumes = {v["name"]: v for v in pod["volumes"]}
                for container in pod["containers"]:
                    where = f"{path.relative_to(KUBERAY).as_posix()} {group} {container['name']}"
                    mounts = [m for m in container["volumeMounts"] if m["mountPath"] == "/dev/shm"]
                    assert len(mounts) == 1, f"{where}: no /dev/shm"
                    empty_dir = volumes[mounts[0]["name"]]["emptyDir"]
                    assert empty_dir["medium"] == "Memory", where
                    shm = _quantity(empty_dir["sizeLimit"])
                    request, limit = (
                        _quantity(container["resources"][kind]["memory"])
                        for kind in ("requests", "limits")
                    )
                    # The object store fits, and the pod is scheduled with memory for it.
                    assert OBJECT_STORE_SHARE * limit <= shm < request <= limit, where
                    checked.append(where)
    assert checked == [
        "rayservice.yaml head ray-head",
        "rayservice.yaml gpu ray-worker",
        "test-set/rayjob.yaml head ray-head",
        "test-set/rayjob.yaml gpu ray-worker",
    ]
    # The gateway runs no Ray node: no object store or DataLoader workers in its pod.
    gateway = _gateway()["spec"]["template"]["spec"]
    assert not any(m["mountPath"] == "/dev/shm" for m in gateway["containers"][0]["volumeMounts"])
    env = {e["name"]: e.get("value") for e in gateway["containers"][0]["env"]}
    assert env["RANGERET_SERVE_URL"].startswith("http://") and "RANGERET_RAY_ADDRESS" not in env


# --- plain machines: the Ray cluster launcher -------------------------------------------------


def _launcher() -> dict:
    return yaml.safe_load((DEPLOY / "ray-cluster.yaml").read_text())


def test_cluster_launcher_config(tmp_path):
    """Token authentication on every node, Serve deployed from the RayService's serveConfigV2
    with `serve deploy` through the head's dashboard, the same paths as on Kubernetes, no Ray
    Client."""
    config = _launcher()
    assert config["provider"]["type"] == "local"
    assert len(config["provider"]["worker_ips"]) == config["max_workers"]
    head, workers = config["head_start_ray_commands"], config["worker_start_ray_commands"]
    assert any("ray start --head" in c for c in head)
    assert any("ray start --address=$RAY_HEAD_IP:6379" in c for c in workers)
    for command in head + workers:
        if "ray start" in command or "serve deploy" in command:
            assert "RAY_AUTH_MODE=token" in command and "RAY_AUTH_TOKEN_PATH=" in command
    text = (DEPLOY / "ray-cluster.yaml").read_text()
    assert "ray://" not in text and "ray-client-server-port" not in text
    (deploy,) = [c for c in head if "serve deploy" in c]
    assert "--address http://127.0.0.1:8265" in deploy
    assert head.index(deploy) > max(i for i, c in enumerate(head) if "ray start --head" in c)
    # The Serve config comes from the RayService manifest the launcher copies to the head.
    ((remote, local),) = config["file_mounts"].items()
    assert (REPO / local / "rayservice.yaml").is_file()
    (extract,) = [c for c in head if "serveConfigV2" in c]
    home = tmp_path / "home"
    (home / Path(remote).name).mkdir(parents=True)
    (home / Path(remote).name / "rayservice.yaml").write_text(
        (KUBERAY / "rayservice.yaml").read_text()
    )
    python = Path(sys.executable)
    subprocess.run(
        ["bash", "-c", extract.replace("/opt/rangeret/bin/python", str(python))],
        env={"HOME": str(home), "PATH": "/usr/bin:/bin"},
        check=True,
        timeout=60,
    )
    written = (home / "serve.yaml").read_text()
    assert "~/serve.yaml" in deploy and serve_config_problems(written) == []
    assert yaml.safe_load(written) == serve_config(_service())
    # The shared mount holds the token; data, models and results appear where the manifests
    # and the Serve config expect them.
    options = config["docker"]["run_options"]
    for volume in (
        "--volume=/mnt/shared:/mnt/shared",
        "--volume=/mnt/shared/data:/data:ro",
        "--volume=/mnt/shared/models:/models:ro",
        "--volume=/mnt/shared/results:/results",
    ):
        assert volume in options


def test_cluster_launcher_gives_dev_shm_room_for_the_object_store():
    from ray.autoscaler._private.util import prepare_config, validate_config

    config = _launcher()
    validate_config(prepare_config(config))  # the launcher's own schema, docker options included
    docker = config["docker"]
    assert docker["image"] == "rangeret:0.1.0"
    pod_memory = [
        _quantity(pod["containers"][0]["resources"]["limits"]["memory"])
        for _, pod in _ray_pod_templates(_service())
    ]
    for role in ("head", "worker"):
        options = docker.get("run_options", []) + docker.get(f"{role}_run_options", [])
        sizes = [_docker_size(o.split("=", 1)[1]) for o in options if o.startswith("--shm-size=")]
        assert len(sizes) == 1, role
        # Ray's default object store stays in /dev/shm whatever the machine's memory: past the
        # threshold Ray caps it at 95 % of /dev/shm...
        assert 0.95 * sizes[0] >= RAY_SHM_THRESHOLD, role
        # ...and on machines sized like the KubeRay pods it is not capped at all.
        assert sizes[0] >= OBJECT_STORE_SHARE * max(pod_memory), role


def test_the_docs_describe_the_new_deployment():
    """No file of deploy/ nor the deployment guide still names the RayCluster manifest, Ray
    Client or the gateway's removed Ray options."""
    files = [
        p
        for p in DEPLOY.rglob("*")
        if p.is_file() and not p.is_relative_to(DEPLOY / "wheelhouse")  # wheels: `make wheelhouse`
    ] + [REPO / "docs" / "deploy.md"]
    for path in files:
        text = path.read_text()
        for stale in ("raycluster.yaml", "ray://", "RANGERET_RAY_ADDRESS", "RANGERET_ACTORS"):
            assert stale not in text, f"{path.relative_to(REPO)}: {stale}"


def _readme_recipe() -> list[str]:
    """The commands of the README's `ray job submit` recipe, one a line, as written."""
    text = (REPO / "README.md").read_text()
    block = next(
        b for b in re.findall(r"```bash\n(.*?)```", text, flags=re.S) if "ray job submit" in b
    )
    lines = block.replace("\\\n", " ").splitlines()
    return [line.split("  #")[0].strip() for line in lines if line.strip()]


def _session_processes(sid: int) -> list[int]:
    """The processes of a session (a daemonised `ray start` leaves its nodes in it)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[3]) == sid:
            found.append(int(stat.parent.name))
    return found


@pytest.mark.slow
@pytest.mark.parametrize("token_exists", [False, True], ids=["no-token-yet", "token-exists"])
def test_the_readmes_ray_job_submit_recipe_runs_as_written(tmp_path, token_exists):
    """The README's commands, in a fresh home folder (no `~/.ray/auth_token`) and in one that
    holds a token already: only the head's ports, the job's paths and the weights are replaced."""
    import contextlib
    import os
    import shutil
    import signal

    from tests.support.workers import build_tree, node_ports

    home = tmp_path / "home"
    (home / ".ray").mkdir(parents=True)
    if token_exists:
        (home / ".ray" / "auth_token").write_text("a" * 64)
    data = build_tree(tmp_path / "data", labelled=1, unlabelled=1)
    weights = small_weights(tmp_path)
    gcs, dash, client, agent, grpc, metrics, nm, om, runtime_env, wmin = node_ports()
    temp = Path(f"/tmp/rr-{os.getpid()}-{gcs}")  # Ray's socket paths must stay short
    ports = (
        f"--port {gcs} --dashboard-port {dash} --ray-client-server-port {client} "
        f"--dashboard-agent-listen-port {agent} --dashboard-agent-grpc-port {grpc} "
        f"--metrics-export-port {metrics} --node-manager-port {nm} --object-manager-port {om} "
        f"--runtime-env-agent-port {runtime_env} --min-worker-port {wmin} "
        f"--max-worker-port {wmin + 40} --num-cpus 2 --temp-dir {temp} "
        "--dashboard-host 127.0.0.1 --disable-usage-stats"
    )
    script = []
    for line in _readme_recipe():
        if line.startswith("python -m workers.predict_job"):
            continue  # the local run beside the recipe
        if line == "ray start --head":
            line = f"{line} {ports}"
        if line.startswith("ray job submit"):
            line = line.replace(
                "ray job submit", f"ray job submit --address http://127.0.0.1:{dash}"
            )
            line = line.replace("--working-dir .", f"--working-dir {REPO}").replace(
                "-- python",
                '--runtime-env-json \'{"excludes": [".venv", ".git", "runs", "tests"]}\' -- python',
            )
            line = line.replace("--dataset /data/semantickitti", f"--dataset {data}").replace(
                "--split test", "--sequences 11"
            )
            line = line.replace("--out /results/pred", f"--out {tmp_path / 'pred'}")
            line = line.replace("/results/submission.zip", str(tmp_path / "submission.zip"))
            line = line.replace(
                "--checkpoint rangeret-kitti-657",
                f"--checkpoint {weights} --height 32 --width 256 --allow-partial",
            )
        script.append(line)
    assert script[:3] == [
        "export RAY_AUTH_MODE=token",
        "ray get-auth-token --generate > /dev/null",
        f"ray start --head {ports}",
    ]
    if token_exists:
        # A relative path names a file in the job's copy of the working directory: one line.
        (submit,) = [line for line in script if line.startswith("ray job submit")]
        relative = submit.replace(f"--dataset {data}", "--dataset runs/nowhere/dataset")
        script.append(f"{relative} || echo relative-refused")
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}
    env.update(HOME=str(home), PATH=f"{Path(sys.executable).parent}{os.pathsep}{env['PATH']}")
    proc = subprocess.Popen(
        ["bash", "-euc", "\n".join(script)],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    try:
        output, _ = proc.communicate(timeout=480)
    finally:
        for pid in _session_processes(proc.pid):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        shutil.rmtree(temp, ignore_errors=True)
    assert proc.returncode == 0, output[-4000:]
    assert "Job 'raysubmit_" in output and "succeeded" in output, output[-3000:]
    assert "AuthenticationError" not in output
    assert validate_submission(
        tmp_path / "submission.zip", data, allow_partial=True, labels=semantickitti()
    ).ok
    assert (home / ".ray" / "auth_token").read_text() != "" and (
        not token_exists or (home / ".ray" / "auth_token").read_text() == "a" * 64
    )
    if token_exists:
        said = " ".join(output.split())
        assert "relative-refused" in output
        assert (
            "--dataset runs/nowhere/dataset is relative, and this Ray job runs in its copy of the "
            "uploaded working directory"
        ) in said, output[-3000:]
        assert (
            "Traceback" not in output.split("relative-refused")[0].rsplit("ray job submit", 1)[-1]
        )


def test_the_health_check_tells_a_ray_pod_from_the_gateway(tmp_path):
    """The image's HEALTHCHECK reads the first process's command line: the ones KubeRay gives the
    Ray containers run `ray start` (as bash's script, or as the process bash became), the
    gateway's is the entrypoint's mode; `ray`'s other commands are not a Ray node."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("healthcheck", DEPLOY / "healthcheck.py")
    healthcheck = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(healthcheck)
    service = _service()
    secrets = secret_values(load_manifests(DEPLOY / "kuberay" / "secrets.example.yaml"))
    commands = [compose(service, group, secrets=secrets).argv for group in ray_groups(service)]
    gateway = deployment_container(
        find(load_manifests(DEPLOY / "kuberay" / "gateway.yaml"), "Deployment"), secrets=secrets
    )
    commands.append(["tini", "--", "/app/deploy/entrypoint.sh", *gateway.args])
    # bash runs the script's last command in its own place: `ray start` itself is then process 1
    # (measured in the image by `make image-test`).
    commands.insert(0, ["/opt/rangeret/bin/python3.11", "/opt/rangeret/bin/ray", "start", "--head"])
    roles = []
    for i, argv in enumerate(commands):
        cmdline = tmp_path / f"cmdline-{i}"
        cmdline.write_bytes("\0".join(argv).encode() + b"\0")
        roles.append(healthcheck.role(cmdline))
    assert roles == ["ray"] * (len(commands) - 1) + ["gateway"]
    cmdline = tmp_path / "cmdline-job"
    cmdline.write_bytes(b"/opt/rangeret/bin/python3\0/opt/rangeret/bin/ray\0job\0list\0")
    assert healthcheck.role(cmdline) == "gateway"
