"""`make image-test`: the CPU image built here with no network, and run as the manifests run it.

Not part of `make test` (it takes minutes and needs root, podman and mmdebstrap); pytest does not
collect this file. Each step is logged with the seconds since the start:

1. the tools: podman (with `tests/image/containers.conf`: runc, cgroupfs, no default ulimits)
   and mmdebstrap;
2. the base: Debian bookworm from Debian's packages, with the system packages the Dockerfile's
   apt step installs for Python 3.11 (`mmdebstrap`), imported as `localhost/rangeret-base:bookworm`;
3. the wheelhouse: `make wheelhouse VARIANT=cpu TORCH_INDEX=` (the CPU torch build pip finds here);
4. the image: `make image VARIANT=cpu CONTAINER=podman OFFLINE=1 BASE_IMAGE=...`, which builds
   `localhost/rangeret:0.1.0-cpu` with `--network none` and `--format docker`; it is left in
   podman's store;
5. the image as built: its HEALTHCHECK and user, exactly the web page's files;
6. `rangeret --help` and `rangeret weights list`, nothing on stderr;
7. the manifests as `kubectl apply -k` gives them, the kustomization's one `images:` line pointed
   at this image;
8. fresh volumes for the three claims (podman volumes owned by root, like a new claim's): uid
   10001 cannot write them yet;
9. the one-off Job of `fill-volumes/`: its root init container gives the volumes to 10001, its
   loader container takes the dataset and the weights streamed in with `tar` and ends when told;
10. the RayService's Ray head, in a container started with the command and environment KubeRay
    composes (`tests/support/kuberay.py`), the Ray token from the Secret's key, the pod's volumes
    and `/dev/shm`;
11. one worker of its GPU group, the same way, joined to the head;
12. `serve deploy` of the RayService's serveConfigV2 with CPU settings (no GPU per replica, one
    replica);
13. the gateway container with the Deployment's args and environment, reaching Serve and the
    Jobs API;
14. `rangeret predict` in a container, and every scan through the gateway labelled the same;
15. a dataset job through the gateway, run as a Ray job in the containers, its predictions the
    same;
16. the image's HEALTHCHECK command passing in every running container (`podman exec`);
17. every container running as uid 10001, and every file on the results volume theirs.

`--reuse-image` skips steps 2 to 4 when the image is in podman's store already (for work on the
later steps).

What it changes from the manifests, so that it runs on one machine: ports (every container is on
the host network, on loopback only), CPU and memory quantities, no GPUs (the Serve replicas ask for
none), one replica of the Serve deployment, and the weights: small networks at 32 x 256 in place
of the published ones, their resolution added to the application's and the gateway's arguments.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import httpx
import yaml

from tests.support.kuberay import (
    KUBERAY,
    compose,
    deployment_container,
    find,
    head_service_fqdn,
    head_service_name,
    kustomize,
    load_manifests,
    quantity,
    secret_values,
    serve_config,
    serve_service_name,
)
from tests.support.paths import REPO

IMAGE = "localhost/rangeret:0.1.0-cpu"
BASE = "localhost/rangeret-base:bookworm"
PYTHON = "python3.11"
MIRROR = os.environ.get("RANGERET_DEBIAN_MIRROR", "http://deb.debian.org/debian")
CONF = Path(__file__).with_name("containers.conf")
#: The kustomization's image line as the operator edits it, pointed at the image built here.
IMAGES = [{"name": "rangeret", "newName": "localhost/rangeret", "newTag": "0.1.0-cpu"}]
SMALL_NET = {"height": 32, "width": 256}
UID = 10001

START = time.monotonic()
ENV = {**os.environ, "CONTAINERS_CONF": str(CONF)}
_step = 0


class Failure(Exception):
    """A check of the image test that did not hold."""


def step(title: str) -> None:
    global _step
    _step += 1
    print(f"\n== [{time.monotonic() - START:6.1f} s] step {_step}: {title}", flush=True)


def note(text: str) -> None:
    print(f"   {text}", flush=True)


def check(condition: object, message: str) -> None:
    if not condition:
        raise Failure(message)


def sh(argv: Sequence[str], *, show: bool = True, **kwargs) -> subprocess.CompletedProcess:
    """Run a command (logged), failing on a non-zero exit."""
    if show:
        note("$ " + shlex.join(argv))
    kwargs.setdefault("check", True)
    kwargs.setdefault("env", ENV)
    return subprocess.run(list(argv), **kwargs)


def podman(*args: str, show: bool = False, **kwargs) -> subprocess.CompletedProcess:
    kwargs.setdefault("capture_output", True)
    kwargs.setdefault("text", True)
    return sh(["podman", *args], show=show, **kwargs)


def wait(what: str, condition: Callable[[], object], timeout: float, watch: Sequence[str] = ()):
    """Poll until `condition()` holds; a Failure naming `what` after `timeout` seconds, or at once
    when one of the containers in `watch` has stopped."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            note(f"{what} ({time.monotonic() - START:.1f} s)")
            return value
        for name in watch:
            state = podman("inspect", "--format", "{{.State.Status}}", name).stdout.strip()
            if state != "running":
                raise Failure(f"{name} stopped ({state}) before: {what}\n{logs(name)}")
        time.sleep(1)
    raise Failure(f"not within {timeout:g} s: {what}")


def logs(name: str, tail: int = 60) -> str:
    got = podman("logs", "--tail", str(tail), name, check=False)
    return (got.stdout + got.stderr).rstrip()


def answers(url: str, token: str | None = None) -> bool:
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    try:
        return httpx.get(url, headers=headers, timeout=5).is_success
    except httpx.TransportError:
        return False


# --- pods as containers ----------------------------------------------------------------------


def _bytes(size: str) -> int:
    return int(quantity(size))


def pod_flags(
    pod: Mapping, container: Mapping, claims: Mapping[str, str], folders: Mapping[str, Path]
) -> list[str]:
    """`podman run` flags for one container of a pod template: the pod's user, group and fsGroup
    (the container's securityContext first), and its volume mounts: a claim as the podman volume
    `claims` gives for its name, read-only where the mount or the pod's volume says so; a ConfigMap
    as the folder `folders` gives for its name; a memory-backed emptyDir at /dev/shm as
    `--shm-size` of its sizeLimit."""
    context = {**(pod.get("securityContext") or {}), **(container.get("securityContext") or {})}
    flags = ["--user", f"{context.get('runAsUser', UID)}:{context.get('runAsGroup', UID)}"]
    if "fsGroup" in context:
        flags += ["--group-add", str(context["fsGroup"])]
    volumes = {v["name"]: v for v in pod.get("volumes", [])}
    for mount in container.get("volumeMounts", []):
        volume = volumes[mount["name"]]
        target = mount["mountPath"]
        if "persistentVolumeClaim" in volume:
            claim = volume["persistentVolumeClaim"]
            ro = mount.get("readOnly") or claim.get("readOnly")
            flags += ["-v", f"{claims[claim['claimName']]}:{target}:{'ro,' if ro else ''}nocopy"]
        elif "configMap" in volume:
            flags += ["-v", f"{folders[volume['configMap']['name']]}:{target}:ro"]
        elif "emptyDir" in volume and target == "/dev/shm":
            check(volume["emptyDir"].get("medium") == "Memory", "/dev/shm is not memory-backed")
            flags += [f"--shm-size={_bytes(volume['emptyDir']['sizeLimit'])}"]
        else:
            raise Failure(f"volume {mount['name']} is not modelled here")
    return flags


def env_flags(env: Mapping[str, str]) -> list[str]:
    return [f for k, v in env.items() for f in ("-e", f"{k}={v}")]


class Run:
    """The containers and volumes of one run, removed at the end (the image stays)."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.prefix = f"rr-image-{os.getpid()}"
        self.containers: list[str] = []
        self.volumes: dict[str, str] = {}

    def volume(self, claim: str) -> str:
        name = f"{self.prefix}-{claim}"
        podman("volume", "create", name, show=True)
        self.volumes[claim] = name
        return name

    def start(self, name: str, flags: Sequence[str], command: Sequence[str] = ()) -> str:
        """A detached container on the host network, with flags before the image and command
        after it."""
        full = f"{self.prefix}-{name}"
        argv = ["run", "-d", "--name", full, "--network", "host", *flags, IMAGE, *command]
        shown = [a if not a.startswith("RAY_AUTH_TOKEN=") else "RAY_AUTH_TOKEN=***" for a in argv]
        note("$ podman " + shlex.join(shown))
        podman(*argv)
        self.containers.append(full)
        return full

    def once(
        self, name: str, flags: Sequence[str], command: Sequence[str], timeout: float = 300
    ) -> tuple[int, str, str]:
        """Run a container to its end: exit code, stdout and stderr read back apart (from
        podman's log of the container, so that podman's own messages are not mixed in)."""
        full = self.start(name, flags, command)
        code = int(podman("wait", full, timeout=timeout).stdout.strip() or "-1")
        out = podman("logs", full)
        podman("rm", full)
        self.containers.remove(full)
        return code, out.stdout, out.stderr

    def close(self) -> None:
        for name in reversed(self.containers):
            podman("rm", "-f", "-t", "5", name, check=False)
        for name in self.volumes.values():
            podman("volume", "rm", "-f", name, check=False)

    def mountpoint(self, claim: str) -> Path:
        return Path(
            podman(
                "volume", "inspect", "--format", "{{.Mountpoint}}", self.volumes[claim]
            ).stdout.strip()
        )


# --- steps -------------------------------------------------------------------------------------


def tools() -> None:
    step("the tools: podman and mmdebstrap")
    for tool in ("podman", "mmdebstrap"):
        check(shutil.which(tool), f"{tool} is missing: make podman installs it")
    note(podman("--version").stdout.strip() + f"; CONTAINERS_CONF={CONF.relative_to(REPO)}")
    info = podman("info", "--format", "{{.Host.OCIRuntime.Name}} {{.Host.CgroupManager}}")
    note(f"runtime and cgroup manager: {info.stdout.strip()}")


def system_packages() -> list[str]:
    """The packages the Dockerfile's apt step installs, for this Python."""
    dockerfile = (REPO / "deploy" / "Dockerfile").read_text()
    listed = re.search(r'packages="([^"]+)"', dockerfile).group(1)
    return listed.replace("${PYTHON}", PYTHON).split()


def base(tmp: Path) -> None:
    step(f"the base: {BASE} from Debian's packages (mmdebstrap), then podman import")
    packages = system_packages()
    tar = tmp / "base.tar"
    sh(
        [
            "mmdebstrap",
            "--quiet",
            "--variant=minbase",
            f"--include={','.join(packages)}",
            "bookworm",
            str(tar),
            MIRROR,
        ]
    )
    note(f"{tar.stat().st_size / 2**20:.0f} MiB with {' '.join(packages)}")
    sh(["podman", "import", "--quiet", "--change", 'CMD ["/bin/bash"]', str(tar), BASE])
    tar.unlink()
    version = podman("run", "--rm", "--network", "none", BASE, PYTHON, "--version").stdout
    note(f"{BASE}: {version.strip()}")


def wheelhouse() -> Path:
    step("the wheelhouse: pip download of the pinned requirements for Python 3.11, x86_64")
    sh(["make", "--no-print-directory", "wheelhouse", "VARIANT=cpu", "TORCH_INDEX="], cwd=REPO)
    folder = REPO / "deploy" / "wheelhouse" / "cpu-py3.11"
    wheels = sorted(p.name for p in folder.glob("*.whl"))
    (torch,) = [w for w in wheels if w.startswith("torch-")]
    note(f"{len(wheels)} wheels in {folder.relative_to(REPO)}, {torch}")
    return folder


def build() -> None:
    step(f"the image: {IMAGE}, built with no network from the wheelhouse (--format docker)")
    started = time.monotonic()
    sh(
        [
            "make",
            "--no-print-directory",
            "image",
            "VARIANT=cpu",
            "CONTAINER=podman",
            "OFFLINE=1",
            f"BASE_IMAGE={BASE}",
            f"IMAGE={IMAGE}",
        ],
        cwd=REPO,
    )
    note(f"built in {time.monotonic() - started:.0f} s")


def inspect_image() -> list[str]:
    """The image's HEALTHCHECK command (checked present) after its user and files are checked."""
    step("the image as built: HEALTHCHECK, user, the web page's files")
    inspected = json.loads(podman("image", "inspect", IMAGE).stdout)[0]
    config = inspected["Config"]
    health = inspected.get("Healthcheck") or config.get("Healthcheck") or {}
    check(health.get("Test", [])[:1] == ["CMD"], f"no HEALTHCHECK in the image: {health}")
    note(f"HEALTHCHECK {health['Test'][1:]}, user {config.get('User')}")
    check(config.get("User") == "rangeret", config.get("User"))
    from service.page_assets import VENDOR_FILES

    listed = podman(
        "run", "--rm", "--network", "none", "--entrypoint", "find", IMAGE,
        "/app/service/web/node_modules", "-type", "f",
    ).stdout.split()  # fmt: skip
    served = {p.removeprefix("/app/service/web/node_modules/") for p in listed}
    expected = {*VENDOR_FILES, "three/LICENSE", "three/package.json", "swagger-ui-dist/LICENSE"}
    check(served == expected, f"the image's npm files: {sorted(served ^ expected)} differ")
    note(f"the web page's npm files, exactly: {len(served)}")
    return health["Test"][1:]


def commands(run: Run) -> None:
    step("rangeret --help and rangeret weights list, nothing on stderr")
    # --help lists the commands every package adds (serve, demo, ros2: pyproject's entry points).
    for argv, expected in (
        (["rangeret", "--help"], ("serve", "demo", "ros2")),
        (["rangeret", "weights", "list"], ("rangeret-kitti-657", "rangeret-panda-600")),
    ):
        code, out, err = run.once("cmd", [], argv)
        check(code == 0, f"{argv}: exit {code}\n{err}")
        check(err == "", f"{argv} wrote to stderr:\n{err}")
        check(all(word in out for word in expected), f"{argv}: {expected} not all in\n{out}")
        note(f"{shlex.join(argv)}: exit 0, {len(out.splitlines())} lines naming "
             f"{', '.join(expected)}; stderr empty")  # fmt: skip


def manifests() -> tuple[list[dict], dict]:
    step("the manifests as kubectl apply -k gives them, the images: line pointed at the image")
    docs = kustomize(KUBERAY, images=IMAGES) + kustomize(KUBERAY / "fill-volumes", images=IMAGES)
    images = sorted(set(re.findall(r'"image": "([^"]+)"', json.dumps(docs))))
    check(images == [IMAGE], images)
    note(f"{len(docs)} documents, every container image {IMAGE}")
    secrets = secret_values(load_manifests(KUBERAY / "secrets.example.yaml"))
    return docs, secrets


def volumes(run: Run, docs: list[dict]) -> dict[str, str]:
    step("fresh volumes for the three claims: uid 10001 cannot write them yet")
    claims = {d["metadata"]["name"]: run.volume(d["metadata"]["name"]) for d in docs
              if d["kind"] == "PersistentVolumeClaim"}  # fmt: skip
    check(sorted(claims) == ["rangeret-data", "rangeret-models", "rangeret-results"], claims)
    # Podman gives a new volume to the user of the first container that mounts it; a new claim's
    # volume is root's, so root mounts these first.
    mounts = [f for claim, volume in claims.items() for f in ("-v", f"{volume}:/{claim}:nocopy")]
    code, out, _ = run.once(
        "root",
        ["--user", "0:0", *mounts],
        ["stat", "-c", "%n %U:%G %a", *(f"/{c}" for c in claims)],
    )
    check(code == 0 and out.count(" root:root 755") == 3, out)
    note("owned by root: " + "; ".join(out.splitlines()))
    code, _, err = run.once(
        "probe",
        ["--user", f"{UID}:{UID}", "-v", f"{claims['rangeret-results']}:/results:nocopy"],
        ["touch", "/results/probe"],
    )
    check(code != 0, "uid 10001 could write a fresh volume without the fill Job")
    note(f"as uid 10001 on the fresh results volume: {err.strip()}")
    return claims


def fill(run: Run, docs: list[dict], claims: Mapping[str, str], stage: Path) -> None:
    step("the fill-volumes Job: its init container (root) chowns, its loader takes the files")
    job = find(docs, "Job")
    pod = job["spec"]["template"]["spec"]
    for init in pod["initContainers"]:
        flags = pod_flags(pod, init, claims, {})
        argv = [*init.get("command", []), *init.get("args", [])]
        code, _, err = run.once(init["name"], ["--entrypoint", json.dumps(argv[:1]), *flags],
                                argv[1:])  # fmt: skip
        check(code == 0, f"init container {init['name']}: exit {code}\n{err}")
        note(f"init container {init['name']} (user {flags[1]}): exit 0")
    (loader,) = pod["containers"]
    name = run.start(loader["name"], pod_flags(pod, loader, claims, {}), loader["args"])
    for folder in ("data", "models"):
        with subprocess.Popen(["tar", "-C", str(stage / folder), "-cf", "-", "."],
                              stdout=subprocess.PIPE) as tar:  # fmt: skip
            podman("exec", "-i", name, "tar", "-C", f"/{folder}", "-xf", "-", stdin=tar.stdout)
        check(tar.returncode == 0, "tar failed")
        note(f"tar -C {folder} -cf - . | podman exec -i {name} tar -C /{folder} -xf -")
    podman("exec", name, "touch", "/tmp/filled", show=True)
    code = int(podman("wait", name, timeout=60).stdout.strip())
    check(code == 0, f"the loader exited {code}\n{logs(name)}")
    note("the loader ended with exit 0")


def free_ports(n: int) -> list[int]:
    from tests.support.workers import free_ports as ports

    return ports(n)


def node_params(ports: list[int], head: bool) -> dict[str, object]:
    """rayStartParams for one node's own ports on the shared host network."""
    gcs, dash, client, agent, grpc, metrics, nm, om, runtime_env, wmin = ports
    params: dict[str, object] = {
        "dashboard-agent-listen-port": agent,
        "dashboard-agent-grpc-port": grpc,
        "metrics-export-port": metrics,
        "node-manager-port": nm,
        "object-manager-port": om,
        "runtime-env-agent-port": runtime_env,
        "min-worker-port": wmin,
        "max-worker-port": wmin + 40,
        "object-store-memory": 400 << 20,
        "disable-usage-stats": "true",
    }
    if head:
        params.update({"port": gcs, "dashboard-host": "127.0.0.1", "dashboard-port": dash,
                       "ray-client-server-port": client})  # fmt: skip
    return params


def cluster_ports() -> list[list[int]]:
    """Ten ports for each of two nodes, the last the first of 41 worker ports, none shared."""
    while True:
        ports = free_ports(20)
        chosen = [ports[:10], ports[10:]]
        ranges = [range(c[-1], c[-1] + 41) for c in chosen]
        singles = [p for c in chosen for p in c[:-1]]
        if not any(p in r for r in ranges for p in singles) and not (
            ranges[0].start in ranges[1] or ranges[1].start in ranges[0]
        ):
            return chosen


def ray_container(
    run: Run, name: str, node, pod: dict, claims: Mapping[str, str], folders: Mapping[str, Path]
) -> str:
    """A Ray container as KubeRay starts it: its composed command replaces the image's
    ENTRYPOINT; the environment KubeRay gives it; the pod's volumes and user."""
    check(node.command == ["/bin/bash", "-c", "--"], node.command)
    container = pod["containers"][0]
    # `ulimit -n 65536` is refused where the machine's hard limit is lower; bash goes on.
    flags = ["--entrypoint", json.dumps(node.command)]
    flags += pod_flags(pod, container, claims, folders) + env_flags(node.env)
    return run.start(name, flags, node.args)


def live_nodes(dashboard: str, token: str) -> int:
    try:
        answer = httpx.get(f"{dashboard}/api/v0/nodes?detail=1", timeout=10,
                           headers={"Authorization": f"Bearer {token}"})  # fmt: skip
        nodes = answer.json()["data"]["result"]["result"]
    except (httpx.HTTPError, KeyError, ValueError):
        return 0
    return sum(1 for n in nodes if n["state"] == "ALIVE")


def tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*.label"))}


def main(argv: Sequence[str] = ()) -> int:
    """Every step; with `--reuse-image` (for working on the later steps) the base, wheelhouse
    and build steps are skipped when the image is in podman's store already."""
    tmp = Path(tempfile.mkdtemp(prefix="rr-image-"))
    run = Run(tmp)
    reuse = (
        "--reuse-image" in argv and podman("image", "exists", IMAGE, check=False).returncode == 0
    )
    try:
        tools()
        if not reuse:
            base(tmp)
            wheelhouse()
            build()
        health = inspect_image()
        commands(run)
        docs, secrets = manifests()
        claims = volumes(run, docs)
        stage = tmp / "stage"
        scans = stage_files(stage)
        fill(run, docs, claims, stage)
        serve(run, docs, secrets, claims, tmp, scans, health)
    except (Failure, subprocess.CalledProcessError, subprocess.TimeoutExpired) as exc:
        print(f"\nFAILED after {time.monotonic() - START:.0f} s: {exc}", flush=True)
        if isinstance(exc, subprocess.CalledProcessError):
            print((exc.stdout or "") + (exc.stderr or ""), flush=True)
        for name in run.containers:
            print(f"\n--- podman logs {name} (end)\n{logs(name)}", flush=True)
        return 1
    finally:
        run.close()
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"\nmake image-test passed in {time.monotonic() - START:.0f} s; {IMAGE} is in "
          "podman's store", flush=True)  # fmt: skip
    return 0


def stage_files(stage: Path) -> list[Path]:
    """The files to copy into the volumes: a small SemanticKITTI tree (sequences 08 and 11) and
    the two models of the models file, small networks under the published names."""
    import torch

    from rangeret.models import build_model
    from tests.support.workers import build_tree, small_weights

    data = build_tree(stage / "data" / "scans", labelled=2, unlabelled=2)
    models = stage / "models"
    models.mkdir(parents=True)
    shutil.move(small_weights(stage), models / "rangeret-kitti-657.pt")
    torch.manual_seed(3)
    panda = build_model("rangeret-cir", 32, 256, num_classes=15, layers=1)
    torch.save(panda.state_dict(), models / "rangeret-panda-600.pt")
    return sorted(data.rglob("*.bin"))


def serve(
    run: Run,
    docs: list[dict],
    secrets: dict,
    claims: Mapping[str, str],
    tmp: Path,
    scans: list[Path],
    health: list[str],
) -> None:
    service = find(docs, "RayService")
    config_map = find(docs, "ConfigMap", "rangeret-models")
    folders = {"rangeret-models": tmp / "etc-rangeret"}
    folders["rangeret-models"].mkdir()
    for key, text in config_map["data"].items():
        (folders["rangeret-models"] / key).write_text(text)
    folders["rangeret-models"].chmod(0o755)

    step("the RayService's Ray head, started as KubeRay starts it")
    head_ports, worker_ports = cluster_ports()
    cluster = service["spec"]["rayClusterConfig"]
    head = compose(service, "head", params=node_params(head_ports, True),
                   resources={"cpu": "2", "memory": "4Gi"}, secrets=secrets)  # fmt: skip
    note(f"KubeRay's command: /bin/bash -c -- {head.args[0]!r}")
    token = head.env["RAY_AUTH_TOKEN"]
    check(token == secrets[cluster["authOptions"]["secretName"]]["auth_token"], "token")
    head_pod = cluster["headGroupSpec"]["template"]["spec"]
    names = [ray_container(run, "ray-head", head, head_pod, claims, folders)]
    dashboard = f"http://127.0.0.1:{head_ports[1]}"
    wait("the head's dashboard answered with the token",
         lambda: answers(f"{dashboard}/api/jobs/", token), 180, names)  # fmt: skip
    check(not answers(f"{dashboard}/api/jobs/"), "the dashboard answered without the token")

    step("a worker of the RayService's GPU group (no GPUs here), joined to the head")
    (group,) = cluster["workerGroupSpecs"]
    worker = compose(
        service, group["groupName"], params=node_params(worker_ports, False),
        resources={"cpu": "2", "memory": "4Gi", "nvidia.com/gpu": None},
        addresses={head_service_fqdn(service): f"127.0.0.1:{head_ports[0]}"}, secrets=secrets,
    )  # fmt: skip
    note(f"KubeRay's command: /bin/bash -c -- {worker.args[0]!r}")
    names.append(ray_container(run, "ray-worker", worker, group["template"]["spec"], claims,
                               folders))  # fmt: skip
    wait("two live nodes", lambda: live_nodes(dashboard, token) == 2, 180, names)

    step("serve deploy of the RayService's serveConfigV2, CPU settings")
    (serve_port,) = free_ports(1)
    config = serve_config(service)
    config["http_options"] = {"host": "127.0.0.1", "port": serve_port}
    app = config["applications"][0]
    app["args"].update(SMALL_NET)
    deployment = app["deployments"][0]
    deployment["autoscaling_config"].update(min_replicas=1, max_replicas=1)
    deployment["ray_actor_options"].update(num_gpus=0, num_cpus=1)
    (tmp / "serve").mkdir()
    (tmp / "serve" / "serve.yaml").write_text(yaml.safe_dump(config))
    (tmp / "serve").chmod(0o755)
    operator_env = {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": token}
    code, out, err = run.once(
        "serve-deploy",
        ["-v", f"{tmp / 'serve'}:/serve:ro", *env_flags(operator_env)],
        ["serve", "deploy", "/serve/serve.yaml", "-a", dashboard],
    )
    check(code == 0, f"serve deploy: exit {code}\n{out}\n{err}")
    note("serve deploy: exit 0")
    serve_url = f"http://127.0.0.1:{serve_port}{app['route_prefix']}"
    wait("the Serve application answered /info", lambda: answers(f"{serve_url}/info"), 420, names)

    step("the gateway container: the Deployment's args and environment")
    (port,) = free_ports(1)
    deployment_doc = find(docs, "Deployment", "rangeret-gateway")
    gateway = deployment_container(
        deployment_doc, secrets=secrets,
        addresses={serve_service_name(service): f"127.0.0.1:{serve_port}",
                   head_service_name(service): f"127.0.0.1:{head_ports[1]}"},
    )  # fmt: skip
    pod = deployment_doc["spec"]["template"]["spec"]
    env = {**gateway.env, "RANGERET_HOST": "127.0.0.1", "RANGERET_PORT": str(port)}
    args = [*gateway.args, *(f"--{k}={v}" for k, v in SMALL_NET.items())]
    note(f"args {args}; RANGERET_SERVE_URL={env['RANGERET_SERVE_URL']}, "
         f"RANGERET_JOBS_ADDRESS={env['RANGERET_JOBS_ADDRESS']}")  # fmt: skip
    flags = pod_flags(pod, pod["containers"][0], claims, folders) + env_flags(env)
    names.append(run.start("gateway", flags, args))
    url = f"http://127.0.0.1:{port}"
    wait("the gateway answered /healthz", lambda: answers(f"{url}/healthz"), 300, names)
    client = httpx.Client(base_url=url, timeout=300,
                          headers={"Authorization": f"Bearer {env['RANGERET_API_TOKEN']}"})  # fmt: skip
    health_details = client.get("/healthz").json()
    check(health_details.get("backend") == "serve", health_details)
    note(f"/healthz: status {health_details['status']}, backend {health_details['backend']}")

    step("rangeret predict in a container, and every scan through the gateway the same")
    predict = ["rangeret", "predict", "-q", "--dataset", "/data/scans", "--out",
               "/results/reference", "--sequences", "08", "11",
               "--checkpoint", "/models/rangeret-kitti-657.pt", "--device", "cpu",
               *(f"--{k}={v}" for k, v in SMALL_NET.items())]  # fmt: skip
    predict_flags = pod_flags(pod, pod["containers"][0], claims, folders)
    code, _, err = run.once("predict", predict_flags, predict)
    check(code == 0, f"rangeret predict: exit {code}\n{err}")
    results = run.mountpoint("rangeret-results")
    reference = tree(results / "reference")
    check(len(reference) == len(scans), sorted(reference))
    for scan in scans:
        answer = client.post("/v1/scans", content=scan.read_bytes(),
                             headers={"Content-Type": "application/octet-stream"})  # fmt: skip
        check(answer.status_code == 200, answer.text)
        key = f"sequences/{scan.parent.parent.name}/predictions/{scan.stem}.label"
        check(answer.content == reference[key], f"{key}: the gateway's labels differ")
    note(f"{len(scans)} scans through the gateway and Serve equal rangeret predict's labels")

    step("a dataset job through the gateway, run as a Ray job in the containers")
    answer = client.post("/v1/jobs", json={"dataset": "/data/scans", "sequences": ["08", "11"]})
    check(answer.status_code == 202, answer.text)
    job = answer.json()["id"]

    def finished() -> dict | None:
        status = client.get(f"/v1/jobs/{job}").json()
        return status if status["state"] in ("succeeded", "failed", "cancelled") else None

    status = wait(f"job {job} finished", finished, 600, names)
    check(status["state"] == "succeeded", status)
    ray_jobs = httpx.get(f"{dashboard}/api/jobs/", timeout=30,
                         headers={"Authorization": f"Bearer {token}"}).json()  # fmt: skip
    mine = {j["submission_id"]: j["status"] for j in ray_jobs
            if j["submission_id"].startswith(job)}  # fmt: skip
    check(list(mine.values()) == ["SUCCEEDED"], mine)
    predictions = tree(results / "gateway" / "jobs" / job / "predictions")
    check(predictions == reference, "the job's predictions differ from rangeret predict's")
    note(f"Ray job {next(iter(mine))} SUCCEEDED; its {len(predictions)} label files equal "
         "rangeret predict's")  # fmt: skip

    step("the image's HEALTHCHECK command in every running container (podman exec)")
    for name in names:
        got = podman("exec", name, *health, check=False)
        check(got.returncode == 0, f"{name}: the health check exited {got.returncode}")
        note(f"podman exec {name} {shlex.join(health)}: exit 0")

    step("every container runs as uid 10001; every file on the results volume is theirs")
    for name in names:
        ids = podman("exec", name, "id", "-u").stdout.strip()
        check(ids == str(UID), f"{name} runs as {ids}")
    note(f"{len(names)} running containers as uid {UID} (and the others from the pod's "
         "securityContext, the image's user)")  # fmt: skip
    owners = {}
    for path in [results, *results.rglob("*")]:
        owners.setdefault(path.lstat().st_uid, []).append(path)
    check(set(owners) == {UID}, {k: [str(p) for p in v[:3]] for k, v in owners.items()})
    note(f"{len(owners[UID])} files and folders on the results volume, all owned by {UID}")
    client.close()


if __name__ == "__main__":
    with contextlib.suppress(KeyboardInterrupt):
        sys.exit(main(sys.argv[1:]))
    sys.exit(130)
