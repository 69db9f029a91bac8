"""Small trees and weights shared by the Ray tests."""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from rangeret.dataset.layout import KITTI_LAYOUT, labels_dir, velodyne_dir
from rangeret.io.scans import KITTI_RECORD, read_labels, read_scan, write_labels, write_scan
from tests.support.paths import data_path, load_vectors


def small_weights(folder: Path) -> Path:
    """The small published-layout state_dict (32 x 256, 2 blocks), saved alone like a release file."""
    fixture = load_vectors("rangeret-cir-32x256-2block.pt")
    path = folder / "cir-small.pt"
    torch.save(fixture["state_dict"], path)
    return path


def build_tree(root: Path, labelled: int = 3, unlabelled: int = 2, seq_test: str = "11") -> Path:
    """Subsampled variants of the real scan: `labelled` in sequence 08 (with labels), the rest in 11."""
    points = read_scan(data_path("semantickitti-scan", "000000.bin"))
    labels = read_labels(data_path("semantickitti-scan", "000000.label"))
    for i in range(labelled + unlabelled):
        seq = "08" if i < labelled else seq_test
        sel = slice(i % 5, None, 9 + i)
        write_scan(
            velodyne_dir(root, seq, layout=KITTI_LAYOUT) / f"{i:06d}.bin",
            points[sel],
            record=KITTI_RECORD,
        )
        if seq == "08":
            write_labels(labels_dir(root, seq, layout=KITTI_LAYOUT) / f"{i:06d}.label", labels[sel])
    return root


def tree_bytes(pred: Path) -> dict[str, bytes]:
    """Every prediction file of a tree, by relative path."""
    return {str(p.relative_to(pred)): p.read_bytes() for p in sorted(pred.rglob("*.label"))}


def kill_actor_when(
    predicate, class_part: str = "ModelWorker", timeout: float = 120.0
) -> threading.Thread:
    """In the background, once `predicate()` holds, SIGKILL the process of one live actor whose
    class name contains `class_part` (a real crash, which Ray must recover from)."""
    from ray._private.state import actors  # the GCS view; needs no dashboard

    killed: list[int] = []

    def run() -> None:
        deadline = time.time() + timeout
        while time.time() < deadline and not predicate():
            time.sleep(0.05)
        while time.time() < deadline:
            for actor in actors().values():
                if (
                    actor["State"] == "ALIVE"
                    and class_part in actor["ActorClassName"]
                    and actor["Pid"]
                ):
                    os.kill(actor["Pid"], signal.SIGKILL)
                    killed.append(actor["Pid"])
                    return
            time.sleep(0.02)

    thread = threading.Thread(target=run, daemon=True)
    thread.killed = killed  # type: ignore[attr-defined]
    thread.start()
    return thread


def free_ports(n: int) -> list[int]:
    """`n` TCP ports free on the loopback right now."""
    socks, ports = [], []
    for _ in range(n):
        s = socket.socket()
        s.bind(("127.0.0.1", 0))
        socks.append(s)
        ports.append(s.getsockname()[1])
    for s in socks:
        s.close()
    return ports


def node_ports(workers: int = 40) -> list[int]:
    """Nine free ports for a node's components and, last, the first of `workers` + 1 worker
    ports, a range that holds none of the nine (Ray refuses a port used twice)."""
    while True:
        ports = free_ports(10)
        first = ports[-1]
        if not any(first <= port <= first + workers for port in ports[:-1]):
            return ports


#: The Ray token of the nodes the tests start (token authentication needs one; without it a head
#: would take `~/.ray/auth_token`, which exists only where an earlier `ray.init()` wrote it).
RAY_TEST_TOKEN = secrets.token_hex(32)


@dataclass
class RayNode:
    """A node started with `ray start`: its GCS address, dashboard URL and environment."""

    gcs: str
    dashboard: str
    env: dict
    bindir: Path
    proc: subprocess.Popen


def serve_deploy(head: RayNode, config: Path, urls: list[str], timeout: float = 240) -> None:
    """`serve deploy CONFIG` on the cluster of `head`, once every one of `urls` answers
    `/info` with 200; the test fails with `serve status` when one does not in time."""
    import httpx
    import pytest

    serve = str(head.bindir / "serve")
    subprocess.run([serve, "deploy", str(config), "-a", head.dashboard], env=head.env, check=True)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            if all(httpx.get(f"{url}/info", timeout=5).status_code == 200 for url in urls):
                return
        except httpx.TransportError:
            pass
        time.sleep(1)
    status = subprocess.run(
        [serve, "status", "-a", head.dashboard], env=head.env, capture_output=True
    )
    pytest.fail(f"{config} did not deploy:\n{status.stdout.decode()}")


@contextlib.contextmanager
def ray_node(
    folder: Path,
    head: RayNode | None = None,
    num_cpus: int = 2,
    num_gpus: int = 0,
    base_env: dict[str, str] | None = None,
):
    """`ray start --block` as a head (or, given `head`, a node joining it) with ports and a temp
    folder of its own, in `base_env` (default: this process's environment), stopped afterwards
    by its own process group only (the Ray CLI's stop command would end every Ray node on the
    machine, other tests' included)."""
    bindir = Path(sys.executable).parent
    env = dict(
        os.environ if base_env is None else base_env,
        PATH=f"{bindir}{os.pathsep}{os.environ['PATH']}",
        RAY_AUTH_MODE="token",
        RAY_AUTH_TOKEN=head.env["RAY_AUTH_TOKEN"] if head else RAY_TEST_TOKEN,
    )
    gcs, dash, client, agent, grpc, metrics, nm, om, runtime_env, wmin = node_ports()
    cmd = [
        str(bindir / "ray"),
        "start",
        "--block",
        "--num-cpus",
        str(num_cpus),
        "--num-gpus",
        str(num_gpus),
        "--dashboard-agent-listen-port",
        str(agent),
        "--dashboard-agent-grpc-port",
        str(grpc),
        "--metrics-export-port",
        str(metrics),
        "--node-manager-port",
        str(nm),
        "--object-manager-port",
        str(om),
        "--min-worker-port",
        str(wmin),
        "--max-worker-port",
        str(wmin + 40),
        "--runtime-env-agent-port",
        str(runtime_env),
        "--disable-usage-stats",
    ]
    temp = Path(f"/tmp/rr-{os.getpid()}-{gcs}")
    if head is None:
        cmd += [
            "--head",
            "--port",
            str(gcs),
            "--include-dashboard",
            "true",
            "--dashboard-host",
            "127.0.0.1",
            "--dashboard-port",
            str(dash),
            "--ray-client-server-port",
            str(client),
            "--temp-dir",
            str(temp),
        ]
        node_gcs, dashboard = f"127.0.0.1:{gcs}", f"http://127.0.0.1:{dash}"
    else:
        cmd += ["--address", head.gcs]
        node_gcs, dashboard = head.gcs, head.dashboard
    log = open(folder / "ray-node.log", "w")  # noqa: SIM115
    proc = subprocess.Popen(
        cmd, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True
    )
    node = RayNode(node_gcs, dashboard, env, bindir, proc)
    try:
        _wait_until_up(node, head is None, log.name)
        yield node
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)
        log.close()
        if head is None:
            shutil.rmtree(temp, ignore_errors=True)


def _wait_until_up(node: RayNode, is_head: bool, log_name: str, timeout: float = 120) -> None:
    """Wait for a head's job server, or for a joining node to count in the cluster."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        if node.proc.poll() is not None:
            raise RuntimeError(f"ray start exited with {node.proc.returncode}; see {log_name}")
        if is_head:
            cmd = [str(node.bindir / "ray"), "job", "list", "--address", node.dashboard]
            if subprocess.run(cmd, env=node.env, capture_output=True, check=False).returncode == 0:
                return
        else:
            cmd = [str(node.bindir / "ray"), "status", "--address", node.gcs]
            status = subprocess.run(cmd, env=node.env, capture_output=True, text=True, check=False)
            if status.stdout.count("node_") >= 2:
                return
        time.sleep(1)
    raise RuntimeError(f"the Ray node did not come up in {timeout:.0f} s; see {log_name}")
