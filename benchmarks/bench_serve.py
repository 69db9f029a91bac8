"""Single scans through the in-process gateway and through the gateway -> Serve path, side by side.

Starts a Ray head of its own (`ray start --head`, loopback, 2 logical CPUs), deploys the Serve
application (`workers.serve_app`, one replica with as many torch threads as the in-process
gateway gets) with `serve deploy`, and two gateways: one labelling in its own process, one with
`--serve-url`. Each runs `rangeret-cir` (8 blocks) at 64 x 512 with kNN, then a near-identity
network (`rangeret-thesis`, 1 block of width 8, no kNN: projection, a few small convolutions and
the labels out), which shows what the hop itself costs. Both paths batch up to `--batch` scans.
For 1, 8 and 32 clients sending the real scan (123,389 points) one request after another it
prints p50 and p95 latency and scans/s, and the Serve path's ratios to the in-process one. Bounded
in count and time; loopback only. Run by hand: `python benchmarks/bench_serve.py`.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np
import torch
import yaml
from _common import REAL_SCAN, require_real_scan
from _gateway import StartedGateway, free_port, load, start_gateway

from rangeret.dataset.profiles import load_profile
from rangeret.models import build_model
from rangeret.models.weights.checkpoint import save_checkpoint

HEIGHT, WIDTH = 64, 512


def make_weights(folder: Path) -> dict[str, dict]:
    """The two networks as project checkpoints at 64 x 512, with the options each path runs."""
    profile = load_profile(None).with_overrides(height=HEIGHT, width=WIDTH)
    records = {
        "label_config": profile.labels,
        "projection": profile.projection,
        "profile": profile.to_dict(),
    }
    torch.manual_seed(0)
    networks = {
        "rangeret-cir, 8 blocks, kNN": (build_model("rangeret-cir", HEIGHT, WIDTH), True),
        "near-identity, no kNN": (
            build_model("rangeret-thesis", HEIGHT, WIDTH, layers=1, dim=8, heads=2),
            False,
        ),
    }
    found = {}
    for i, (name, (network, knn)) in enumerate(networks.items()):
        path = folder / f"net{i}.pt"
        save_checkpoint(path, network, **records)
        found[name] = {"checkpoint": str(path), "knn": knn}
    return found


def ray_head(folder: Path, cpus: int) -> tuple[subprocess.Popen, str, dict]:
    """`ray start --head --block` on loopback with a token of its own; its dashboard URL."""
    bindir = Path(sys.executable).parent
    env = dict(
        os.environ,
        PATH=f"{bindir}{os.pathsep}{os.environ['PATH']}",
        RAY_AUTH_MODE="token",
        RAY_AUTH_TOKEN=os.urandom(16).hex(),
    )
    gcs, dashboard, client = free_port(), free_port(), free_port()
    cmd = [
        *(str(bindir / "ray"), "start", "--head", "--block", "--num-cpus", str(cpus)),
        *("--port", str(gcs), "--dashboard-host", "127.0.0.1", "--dashboard-port", str(dashboard)),
        *("--ray-client-server-port", str(client), "--temp-dir", str(folder / "ray")),
        "--disable-usage-stats",
    ]
    log = open(folder / "ray.log", "wb")  # noqa: SIM115
    proc = subprocess.Popen(
        cmd, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True
    )
    url = f"http://127.0.0.1:{dashboard}"
    deadline = time.time() + 180
    while time.time() < deadline:
        listed = subprocess.run(
            [str(bindir / "ray"), "job", "list", "--address", url], env=env, capture_output=True
        )
        if listed.returncode == 0:
            return proc, url, env
        time.sleep(1)
    os.killpg(proc.pid, signal.SIGKILL)
    sys.exit(f"the Ray head did not start; see {folder / 'ray.log'}")


def deploy(folder: Path, dashboard: str, env: dict, args: dict, cpus: int, port: int) -> str:
    """`serve deploy` of the application with these arguments (Serve's proxy on `port`, which
    stays the same for the life of the cluster); its URL once it answers."""
    config = {
        "http_options": {"host": "127.0.0.1", "port": port},
        "applications": [
            {
                "name": "rangeret",
                "route_prefix": "/rangeret",
                "import_path": "workers.serve_app:build_app",
                "args": args,
                "deployments": [
                    {
                        "name": "ScanModel",
                        "num_replicas": 1,
                        "max_ongoing_requests": 64,
                        "max_queued_requests": -1,
                        "ray_actor_options": {"num_cpus": cpus, "num_gpus": 0},
                    }
                ],
            }
        ],
    }
    path = folder / "serve.yaml"
    path.write_text(yaml.safe_dump(config))
    serve = str(Path(sys.executable).parent / "serve")
    subprocess.run([serve, "deploy", str(path), "-a", dashboard], env=env, check=True)
    url = f"http://127.0.0.1:{port}/rangeret"
    deadline = time.time() + 300
    while time.time() < deadline:
        try:
            info = httpx.get(url + "/info", timeout=5)
            if info.status_code == 200 and info.json()["checkpoint"] == args["checkpoint"]:
                return url
        except (httpx.HTTPError, ValueError, KeyError):
            pass
        time.sleep(1)
    sys.exit("the Serve application did not answer in 300 s")


def figures(wall: float, latencies: list[float]) -> dict[str, float]:
    """p50 and p95 in ms, scans/s."""
    return {
        "p50": 1e3 * statistics.median(latencies),
        "p95": 1e3 * float(np.percentile(latencies, 95)),
        "rate": len(latencies) / wall,
    }


def gateway(weights: dict, state: Path, batch: int, wait_ms: float, serve_url: str | None):
    """A gateway process for this network, in-process or in front of the Serve application."""
    options = ["--checkpoint", weights["checkpoint"], "--device", "cpu"]
    if not weights["knn"]:
        options.append("--no-knn")
    settings = {
        "RANGERET_STATE_DIR": str(state),
        "RANGERET_BATCH_SIZE": str(batch),
        "RANGERET_BATCH_WAIT_MS": str(wait_ms),
        "RANGERET_MAX_QUEUED_SCANS": "512",
    }
    if serve_url:
        settings["RANGERET_SERVE_URL"] = serve_url
    state.mkdir(parents=True, exist_ok=True)
    return start_gateway(options, settings, state / "gateway.log", serve_url or "in-process")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--clients", type=int, nargs="+", default=[1, 8, 32])
    parser.add_argument("--requests", type=int, default=32, help="requests per client count")
    parser.add_argument("--echo-requests", type=int, default=256)
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--wait-ms", type=float, default=10.0)
    args = parser.parse_args()
    require_real_scan()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit("stopped by SIGTERM"))  # runs the clean-up
    body = REAL_SCAN.read_bytes()
    cpus = os.cpu_count() or 1
    print(
        f"the real scan (123,389 points) at {HEIGHT} x {WIDTH}, batches of up to {args.batch}, "
        f"{cpus} CPUs; p50/p95 in ms"
    )
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        nets = make_weights(folder)
        head, dashboard, env = ray_head(folder, cpus)
        proxy_port = free_port()
        try:
            for name, weights in nets.items():
                serve_args = {
                    "checkpoint": weights["checkpoint"],
                    "device": "cpu",
                    "knn": weights["knn"],
                    "batch_size": args.batch,
                    "batch_wait_ms": args.wait_ms,
                }
                url = deploy(folder, dashboard, env, serve_args, cpus, proxy_port)
                total = args.echo_requests if not weights["knn"] else args.requests
                print(f"\n== {name} ({total} requests per client count)")
                for clients in args.clients:
                    rows = {}
                    for path in ("in-process", "serve"):
                        state = folder / f"state-{path}"
                        gw: StartedGateway = gateway(
                            weights,
                            state,
                            args.batch,
                            args.wait_ms,
                            url if path == "serve" else None,
                        )
                        try:
                            scans = max(1, total // clients)
                            rows[path] = figures(*asyncio.run(load(gw.url, body, clients, scans)))
                        finally:
                            gw.stop()
                    local, remote = rows["in-process"], rows["serve"]
                    for path, r in rows.items():
                        print(
                            f"{clients:3d} client(s)  {path:<10}  p50 {r['p50']:8.1f}  p95 "
                            f"{r['p95']:8.1f}  {r['rate']:7.2f} scans/s"
                        )
                    print(
                        f"{clients:3d} client(s)  Serve hop: p50 {remote['p50'] - local['p50']:+.1f} ms, "
                        f"throughput x{remote['rate'] / local['rate']:.2f} of in-process"
                    )
        finally:
            os.killpg(head.pid, signal.SIGTERM)
            try:
                head.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(head.pid, signal.SIGKILL)


if __name__ == "__main__":
    main()
