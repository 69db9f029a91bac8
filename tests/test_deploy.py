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
    for source in re.findall(r"^COPY (?!--from=)(.+) \S+$", dockerfile, flags=re.M):
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


def test_the_image_carries_the_web_page_built_in_a_pinned_node_stage():
    """The node stage installs the page's locked npm packages; the image takes every file the
    gateway serves from them (and three.js's licence), where the package data picks them up."""
    from fnmatch import fnmatch

    import tomllib

    from service.page_assets import VENDOR_FILES, WEB_DIR

    dockerfile = (DEPLOY / "Dockerfile").read_text()
    stage = re.search(r"^FROM node:(\S+) AS web$", dockerfile, flags=re.M)
    assert stage and re.fullmatch(r"\d+\.\d+\.\d+-[a-z]+-slim", stage.group(1)), stage
    assert "COPY service/web/package.json service/web/package-lock.json /web/" in dockerfile
    assert "RUN npm ci " in dockerfile
    copied = []
    for sources, target in re.findall(r"^COPY --from=web (.+) (\S+)$", dockerfile, flags=re.M):
        for source in sources.split():
            name = source.removeprefix("/web/node_modules/")
            assert target == f"/app/service/web/node_modules/{name.rsplit('/', 1)[0]}/", source
            copied.append(name)
    assert set(VENDOR_FILES) | {"three/LICENSE"} <= set(copied)
    # The copy comes before the project is installed, and the wheel's package data holds it.
    assert dockerfile.index("COPY --from=web") < dockerfile.index("RUN pip install --no-deps .")
    patterns = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"][
        "package-data"
    ]["service"]
    served = [f"web/node_modules/{name}" for name in (*VENDOR_FILES, "three/LICENSE")]
    served += [f"web/src/{p.name}" for p in (WEB_DIR / "src").iterdir()] + ["web/index.html"]
    for path in served:
        assert any(fnmatch(path, pattern) for pattern in patterns), path
    # npm ci installs exactly the version package.json pins.
    package = json.loads((WEB_DIR / "package.json").read_text())
    lock = json.loads((WEB_DIR / "package-lock.json").read_text())
    pinned = package["dependencies"]["three"]
    assert re.fullmatch(r"\d+\.\d+\.\d+", pinned)
    assert lock["packages"]["node_modules/three"]["version"] == pinned


def test_the_image_installs_every_dependency_of_the_project():
    """The image installs the project with --no-deps, so its pip lines must name every
    dependency pyproject declares (torch comes from the CUDA wheel index)."""
    import tomllib

    dockerfile = (DEPLOY / "Dockerfile").read_text()
    installed = " ".join(re.findall(r"pip install[^&]*", dockerfile.replace("\\\n", " ")))
    declared = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    for requirement in declared:
        name = re.split(r"[<>=\[ ]", requirement, maxsplit=1)[0]
        assert re.search(rf"(^|[\s\"]){re.escape(name)}([\s\"\[]|$)", installed), name


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


def _ray_pod_templates(doc: dict) -> list[tuple[str, dict]]:
    """(group name, pod spec) of every Ray pod a manifest defines: a RayCluster's, a RayJob's
    rayClusterSpec and a RayService's rayClusterConfig, head and worker groups."""
    spec = doc.get("spec", {})
    cluster = {
        "RayCluster": spec,
        "RayJob": spec.get("rayClusterSpec"),
        "RayService": spec.get("rayClusterConfig"),
    }.get(doc["kind"])
    if not cluster:
        return []
    groups = [("head", cluster["headGroupSpec"])]
    groups += [(g["groupName"], g) for g in cluster.get("workerGroupSpecs", [])]
    return [(name, group["template"]["spec"]) for name, group in groups]


def test_every_ray_container_mounts_a_memory_backed_dev_shm_for_the_object_store():
    checked = []
    for path in sorted((DEPLOY / "kuberay").glob("*.yaml")):
        for doc in _docs(path):
            if doc["kind"] == "RayJob":
                assert doc["spec"].get("clusterSelector") or doc["spec"].get("rayClusterSpec")
            for group, pod in _ray_pod_templates(doc):
                volumes = {v["name"]: v for v in pod["volumes"]}
                for container in pod["containers"]:
                    where = f"{path.name} {group} {container['name']}"
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
        "raycluster.yaml head ray-head",
        "raycluster.yaml gpu ray-worker",
    ]
    # The gateway is a Ray Client: no object store or DataLoader workers in its pod.
    gateway = _docs(DEPLOY / "kuberay" / "gateway.yaml")[0]["spec"]["template"]["spec"]
    env = {e["name"]: e.get("value") for e in gateway["containers"][0]["env"]}
    assert env["RANGERET_RAY_ADDRESS"].startswith("ray://")


def test_cluster_launcher_gives_dev_shm_room_for_the_object_store():
    from ray.autoscaler._private.util import prepare_config, validate_config

    config = yaml.safe_load((DEPLOY / "ray-cluster.yaml").read_text())
    validate_config(prepare_config(config))  # the launcher's own schema, docker options included
    docker = config["docker"]
    assert docker["image"] == "rangeret:0.1.0"
    cluster = _docs(DEPLOY / "kuberay" / "raycluster.yaml")[0]
    pod_memory = [
        _quantity(pod["containers"][0]["resources"]["limits"]["memory"])
        for _, pod in _ray_pod_templates(cluster)
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
        # The shared mount that holds the token, the dataset and the results.
        assert "--volume=/mnt/shared:/mnt/shared" in options


# Published torch builds, from PyTorch's CUDA support matrix and the wheels on PyPI: CUDA
# major.minor and CPython versions per torch minor release. Add the release before pinning it.
TORCH_CUDA_BUILDS = {"2.13": {"12.6", "13.0", "13.2"}}
TORCH_PYTHONS = {"2.13": {"3.10", "3.11", "3.12", "3.13", "3.14"}}
# The python3 of each Ubuntu release the NVIDIA CUDA images are built on.
UBUNTU_PYTHON = {"22.04": "3.10", "24.04": "3.12"}


def test_image_base_cuda_and_torch_wheel_match():
    dockerfile = (DEPLOY / "Dockerfile").read_text()
    before_from = dockerfile.split("\nFROM ", 1)[0]
    args = dict(re.findall(r"^ARG (\w+)=(\S+)$", before_from, flags=re.M))
    base = re.search(r"^FROM (\S+)$", dockerfile, flags=re.M).group(1)
    base = re.sub(r"\$\{(\w+)\}", lambda m: args[m.group(1)], base)
    match = re.fullmatch(r"nvidia/cuda:((\d+)\.(\d+)\.\d+)-cudnn-runtime-ubuntu(\d+\.\d+)", base)
    assert match, base
    cuda_version, major, minor, ubuntu = match.groups()

    # torch: the project's pin (the Makefile's default TORCH_SPEC), set only in constraints.txt.
    makefile = (REPO / "Makefile").read_text()
    torch_spec = re.search(r"^TORCH_SPEC \?= (\S+)$", makefile, flags=re.M).group(1)
    constraints = (DEPLOY / "constraints.txt").read_text()
    assert re.search(r"^torch==\S+$", constraints, flags=re.M).group(0) == torch_spec
    torch = torch_spec.split("==")[1]
    assert set(re.findall(r"torch==(\d[\w.]*\d)", dockerfile)) <= {torch}
    assert re.search(r"-c deploy/constraints\.txt torch\b", dockerfile)

    # The wheel index is derived from the CUDA_VERSION the base image sets (its tag's version).
    cuda_expr = re.search(r'cuda="(\$\{CUDA_VERSION[^"]*\})"', dockerfile).group(1)
    index = re.search(r'--extra-index-url "(https://download\.pytorch\.org/whl/[^"]+)"', dockerfile)
    derived = subprocess.run(
        ["sh", "-c", f'cuda="{cuda_expr}"; printf %s "{index.group(1)}"'],
        env={"CUDA_VERSION": cuda_version},
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert derived == f"https://download.pytorch.org/whl/cu{major}{minor}"
    assert "torch.version.cuda == '$cuda'" in dockerfile  # the build checks the wheel's CUDA
    release = ".".join(torch.split(".")[:2])
    assert f"{major}.{minor}" in TORCH_CUDA_BUILDS[release]

    # The base image's Python, the one the venv is made with, has torch wheels (cp3XX).
    python = UBUNTU_PYTHON[ubuntu]
    assert set(re.findall(r"python3\.\d+", dockerfile)) == {f"python{python}"}
    assert python in TORCH_PYTHONS[release]

    # The documented build commands name the same pin.
    for doc in (DEPLOY / "README.md", REPO / "docs" / "deploy.md", DEPLOY / "Dockerfile"):
        builds = re.findall(
            r"docker build -f deploy/Dockerfile --build-arg CUDA_VERSION=(\S+) -t \S+ \.",
            doc.read_text(),
        )
        assert builds == [cuda_version], doc.name


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
