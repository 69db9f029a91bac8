"""Concurrent single-scan load on the HTTP gateway over loopback: throughput, p50/p99, batching gain.

Starts a gateway of its own (`python -m service`, in-process worker, the small published-layout
weights of the test vectors at 32 x 256) once per configuration, warms it up, then lets `--clients`
clients each send `--scans` requests one after another (a subsampled real scan) and reports
scans/s and latency percentiles, first with batch size 1, then with request batching. Bounded in
count and time; loopback only. Run by hand: `python benchmarks/bench_gateway.py`.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import statistics
import tempfile
from pathlib import Path

import httpx
import numpy as np
import torch
from _common import REAL_SCAN, require_real_scan, small_state_dict
from _gateway import StartedGateway, load, start_gateway

from rangeret.io.scans import read_scan


def launch(weights: Path, state: Path, batch: int, wait_ms: float, device: str) -> StartedGateway:
    """A gateway process with these batching settings, once it answers /healthz."""
    options = ["--checkpoint", str(weights), "--height", "32", "--width", "256"]
    settings = {
        "RANGERET_STATE_DIR": str(state),
        "RANGERET_BATCH_SIZE": str(batch),
        "RANGERET_BATCH_WAIT_MS": str(wait_ms),
    }
    return start_gateway([*options, "--device", device], settings, state / "gateway.log", "")


def percentile(values: list[float], q: float) -> float:
    """The q-th percentile (0..100) by linear interpolation."""
    return float(np.percentile(np.asarray(values), q))


def run_config(
    weights: Path, body: bytes, args: argparse.Namespace, batch: int, wait_ms: float
) -> dict[str, float]:
    """Start a gateway, load it, stop it; its figures."""
    with tempfile.TemporaryDirectory() as state:
        gw = launch(weights, Path(state), batch, wait_ms, args.device)
        try:
            wall, latencies = asyncio.run(
                load(gw.url, body, args.clients, args.scans, args.timeout, warmup=3)
            )
            metrics = httpx.get(gw.url + "/metrics", timeout=10).text
        finally:
            gw.stop()
    batches = sum(
        float(line.split()[-1])
        for line in metrics.splitlines()
        if line.startswith("rangeret_batch_scans_count")
    )
    return {
        "throughput": len(latencies) / wall,
        "p50": 1e3 * statistics.median(latencies),
        "p99": 1e3 * percentile(latencies, 99),
        "mean_batch": (len(latencies) + 3) / batches if batches else float("nan"),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--clients", type=int, default=8)
    parser.add_argument("--scans", type=int, default=25, help="requests per client")
    parser.add_argument(
        "--stride", type=int, default=8, help="keep every N-th point of the real scan"
    )
    parser.add_argument("--batch", type=int, default=4, help="batch size of the batching run")
    parser.add_argument(
        "--wait-ms", type=float, default=20.0, help="batch wait of the batching run"
    )
    parser.add_argument("--device", default="auto")
    parser.add_argument("--timeout", type=float, default=300.0, help="seconds one request may take")
    args = parser.parse_args()
    require_real_scan()
    points = read_scan(REAL_SCAN)[:: args.stride]
    body = points.tobytes()
    with tempfile.TemporaryDirectory() as tmp:
        weights = Path(tmp) / "cir-small.pt"
        torch.save(small_state_dict(), weights)
        print(
            f"{args.clients} clients x {args.scans} scans of {len(points):,} points, small rangeret-cir at 32x256, "
            f"device {args.device}, {os.cpu_count()} CPUs"
        )
        single = run_config(weights, body, args, 1, 0.0)
        batched = run_config(weights, body, args, args.batch, args.wait_ms)
    for name, r in (
        ("batch 1", single),
        (f"batch {args.batch}, wait {args.wait_ms:g} ms", batched),
    ):
        print(
            f"{name:<24} {r['throughput']:7.2f} scans/s   p50 {r['p50']:8.1f} ms   p99 {r['p99']:8.1f} ms   "
            f"mean batch {r['mean_batch']:.2f}"
        )
    print(
        f"batching gain: throughput x{batched['throughput'] / single['throughput']:.2f}, "
        f"p50 x{single['p50'] / batched['p50']:.2f}, p99 x{single['p99'] / batched['p99']:.2f} (higher is better)"
    )


if __name__ == "__main__":
    main()
