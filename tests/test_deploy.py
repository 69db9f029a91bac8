"""Deployment files: manifests and configs parse and name entrypoints, modules and flags that
exist; and a head plus a second node run a simulated split through `ray job submit`."""

from __future__ import annotations

import json
import re
import shlex
import subprocess
from pathlib import Path

import pytest
import yaml
from workers_helpers import ray_node, small_weights

from rangeret.sim import SensorConfig, simulate_dataset
from rangeret.submission import TEST_SEQUENCES, validate_submission
from workers.predict_job import build_parser as job_parser

REPO = Path(__file__).resolve().parent.parent
DEPLOY = REPO / "deploy"


def _docs(path: Path) -> list[dict]:
    return [d for d in yaml.safe_load_all(path.read_text()) if d]


def test_kuberay_manifests_parse_and_fit_together():
    kinds = {
        p.name: [d["kind"] for d in _docs(p)] for p in sorted((DEPLOY / "kuberay").glob("*.yaml"))
    }
    assert kinds == {
        "gateway.yaml": ["Deployment", "Service"],
        "raycluster.yaml": ["RayCluster"],
        "rayjob.yaml": ["RayJob"],
        "secrets.example.yaml": ["Secret"],
        "storage.yaml": ["PersistentVolumeClaim"] * 3,
    }
    claims = {d["metadata"]["name"] for d in _docs(DEPLOY / "kuberay" / "storage.yaml")}
    secret = _docs(DEPLOY / "kuberay" / "secrets.example.yaml")[0]
    text = "".join(
        (DEPLOY / "kuberay" / n).read_text()
        for n in ("raycluster.yaml", "rayjob.yaml", "gateway.yaml")
    )
    for claim in re.findall(r"claimName: ([\w-]+)", text):
        assert claim in claims
    for key in re.findall(r"secretKeyRef: \{name: rangeret-tokens, key: ([\w-]+)\}", text):
        assert key in secret["stringData"]

    cluster = _docs(DEPLOY / "kuberay" / "raycluster.yaml")[0]["spec"]
    assert cluster["rayVersion"] == "2.60.0"
    assert cluster["headGroupSpec"]["rayStartParams"]["num-gpus"] == "0"
    gpu_group = cluster["workerGroupSpecs"][0]
    assert gpu_group["rayStartParams"]["num-gpus"] == "1"
    limits = gpu_group["template"]["spec"]["containers"][0]["resources"]["limits"]
    assert limits["nvidia.com/gpu"] == "1"
    env = {e["name"] for e in gpu_group["template"]["spec"]["containers"][0]["env"]}
    assert {"RAY_AUTH_MODE", "RAY_AUTH_TOKEN"} <= env


def test_rayjob_entrypoint_names_a_module_and_flags_that_exist():
    job = _docs(DEPLOY / "kuberay" / "rayjob.yaml")[0]
    argv = shlex.split(job["spec"]["entrypoint"])
    assert argv[:3] == ["python", "-m", "workers.predict_job"]
    args = job_parser().parse_args(argv[3:])
    assert args.split == "test" and str(args.submission).endswith(".zip")
    assert str(args.out).startswith("/results") and str(args.dataset).startswith("/data")


def test_container_files_exist_and_pins_agree():
    dockerfile = (DEPLOY / "Dockerfile").read_text()
    for source in re.findall(r"^COPY (.+) \S+$", dockerfile, flags=re.M):
        for item in source.split():
            assert (REPO / item).exists(), item
    assert "USER rangeret" in dockerfile and "HEALTHCHECK" in dockerfile
    pins = dict(
        line.split("==")
        for line in (DEPLOY / "constraints.txt").read_text().splitlines()
        if line and not line.startswith("#")
    )
    pyproject = (REPO / "pyproject.toml").read_text()
    assert f"ray[default,data]=={pins['ray']}" in pyproject
    entry = (DEPLOY / "entrypoint.sh").read_text()
    for mode in ("gateway)", "ray-head)", "ray-worker)"):
        assert mode in entry
    subprocess.run(["bash", "-n", str(DEPLOY / "entrypoint.sh")], check=True)


def test_cluster_launcher_config():
    config = yaml.safe_load((DEPLOY / "ray-cluster.yaml").read_text())
    assert config["provider"]["type"] == "local"
    assert len(config["provider"]["worker_ips"]) == config["max_workers"]
    assert any("--head" in c for c in config["head_start_ray_commands"])
    assert all(
        "RAY_AUTH_MODE=token" in c
        for c in config["head_start_ray_commands"] + config["worker_start_ray_commands"]
        if "start" in c
    )


@pytest.mark.slow
def test_two_nodes_run_a_simulated_split_through_ray_job_submit(tmp_path):
    """`ray job submit` to a head started with `ray start --head` (token authentication) that a
    second node joined: predictions, the evaluation report and a valid (partial) archive."""
    data, out, archive = tmp_path / "data", tmp_path / "pred", tmp_path / "submission.zip"
    report = tmp_path / "report.json"
    simulate_dataset(
        data,
        {"08": 2, **{s: 1 for s in TEST_SEQUENCES[:3]}},
        labelled=["08"],
        sensor=SensorConfig(beams=32, azimuth_steps=512),
        seed=3,
    )
    weights = small_weights(tmp_path)
    with ray_node(tmp_path, num_cpus=1) as head, ray_node(tmp_path / "..", head=head, num_cpus=2):
        status = subprocess.run(
            [str(head.bindir / "ray"), "status", "--address", head.gcs],
            env=head.env,
            capture_output=True,
            text=True,
            check=True,
        )
        assert status.stdout.count("node_") >= 2
        cmd = [
            str(head.bindir / "ray"),
            "job",
            "submit",
            "--address",
            head.dashboard,
            "--working-dir",
            str(REPO),
            "--runtime-env-json",
            json.dumps({"excludes": [".venv", ".git", "runs"]}),
            "--",
            "python",
            "-m",
            "workers.predict_job",
            "--dataset",
            str(data),
            "--sequences",
            "08",
            *TEST_SEQUENCES,
            "--report",
            str(report),
            "--out",
            str(out),
            "--submission",
            str(archive),
            "--allow-partial",
            "--checkpoint",
            str(weights),
            "--height",
            "32",
            "--width",
            "256",
            "--read-cpus",
            "0.25",
            "--actors",
            "2",
            "--actor-cpus",
            "1",
        ]
        run = subprocess.run(
            cmd, env=head.env, capture_output=True, text=True, timeout=600, check=False
        )
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    assert "5 written" in run.stdout
    check = validate_submission(archive, data, allow_partial=True)
    assert check.ok and check.scans == 3
    assert json.loads(report.read_text())["num_scans"] == 2
    assert len(list(out.rglob("*.label"))) == 5


def test_gateway_manifest_names_the_serve_command_and_settings():
    from rangeret.cli import build_parser
    from service.settings import Settings

    deployment = _docs(DEPLOY / "kuberay" / "gateway.yaml")[0]
    container = deployment["spec"]["template"]["spec"]["containers"][0]
    assert container["args"][0] == "gateway"
    args = build_parser().parse_args(["serve", *container["args"][1:]])
    assert str(args.checkpoint).startswith("/models/")
    fields = {f"RANGERET_{name.upper()}" for name in Settings.model_fields}
    for env in container["env"]:
        if env["name"].startswith("RANGERET_"):
            assert env["name"] in fields, env["name"]
