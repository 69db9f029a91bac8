"""Several models in one gateway: what a model switch costs, throughput with 1, 2 and 3 models,
and the memory `--max-loaded` bounds.

Starts gateways of its own (`python -m service --models`, in-process networks, checkpoints of the
release's rangeret-cir layout with their own random weights):

- switch cost: with `--max-loaded 1`, requests alternating between two models each load the
  other network (its checkpoint read again); their latency is set beside requests that stay on
  one model, median of `--switches` each, in one run (at `--height` x `--width`, `--blocks`);
- throughput: `--clients` clients each send `--scans` requests spread round-robin over 1, 2 and 3
  models, every model loaded (`--max-loaded` = models), as scans/s and p50/p99 latency (the same
  shape);
- memory: the resident set (VmRSS, Linux) of a gateway of one model, of eight models with
  `--max-loaded 1` and of eight with `--max-loaded 8`, each after `--rounds` rounds of requests
  alternating over its models (the one-model gateway gets as many requests), the networks of the
  release's shape (8 blocks, 64 x 1024): the first two should hold about the same, the third
  seven networks more.

`--sections` picks the parts to run. Bounded in count and time; loopback only. Run by hand:
`python benchmarks/bench_model_switch.py`.
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np
import torch
import yaml
from _common import REAL_SCAN, require_real_scan
from _gateway import OCTET, StartedGateway, rss_mib, start_gateway

from rangeret.io.scans import read_scan
from rangeret.models import build_model

NAMES = ("one", "two", "three")
#: The eight models of the memory section.
EIGHT = tuple(f"m{i}" for i in range(8))
#: The release's network: (height, width, blocks).
RELEASE = (64, 1024, 8)
SECTIONS = ("switch", "throughput", "memory")


def checkpoints(
    folder: Path, names: tuple[str, ...], height: int, width: int, blocks: int
) -> dict[str, Path]:
    """Published-format rangeret-cir files named `names`, each of its own random weights."""
    paths = {}
    for seed, name in enumerate(names):
        torch.manual_seed(seed)
        network = build_model("rangeret-cir", height, width, num_classes=20, layers=blocks)
        paths[name] = folder / f"{name}.pt"
        torch.save(network.state_dict(), paths[name])
    return paths


def launch(
    folder: Path,
    weights: dict[str, Path],
    names: tuple[str, ...],
    max_loaded: int,
    args,
    shape: tuple[int, int] | None = None,
) -> StartedGateway:
    """A gateway serving `names` at `shape` (default `--height` x `--width`), at most
    `max_loaded` networks loaded."""
    height, width = shape or (args.height, args.width)
    models = folder / f"models-{len(names)}-{max_loaded}.yaml"
    entries = {name: {"checkpoint": str(weights[name])} for name in names}
    models.write_text(yaml.safe_dump({"default": names[0], "models": entries}, sort_keys=False))
    options = ["--models", str(models), "--height", str(height), "--width", str(width)]
    options += ["--device", args.device, "--max-loaded", str(max_loaded)]
    state = folder / f"state-{len(names)}-{max_loaded}"
    state.mkdir()
    return start_gateway(options, {"RANGERET_STATE_DIR": str(state)}, state / "gateway.log", "")


def timed(client: httpx.Client, body: bytes, model: str) -> float:
    """Seconds one request for `model` takes."""
    start = time.perf_counter()
    client.post(
        "/v1/scans", params={"model": model}, content=body, headers=OCTET
    ).raise_for_status()
    return time.perf_counter() - start


def switch_cost(folder: Path, weights: dict[str, Path], body: bytes, args) -> dict[str, float]:
    """Median latency of requests that stay on one model and of requests that switch."""
    gw = launch(folder, weights, NAMES[:2], 1, args)
    try:
        with httpx.Client(base_url=gw.url, timeout=args.timeout) as client:
            timed(client, body, "one")
            stay, switch = [], []
            for _ in range(args.switches):
                stay.append(timed(client, body, "one"))
                switch.append(timed(client, body, "two"))  # loads two, evicts one
                switch.append(timed(client, body, "one"))  # loads one again
                stay.append(timed(client, body, "one"))
            loads = [m["id"] for m in client.get("/v1/models").json()["models"] if m["loaded"]]
    finally:
        gw.stop()
    assert loads == ["one"], loads
    return {"stay_s": statistics.median(stay), "switch_s": statistics.median(switch)}


async def round_robin(url: str, body: bytes, names: tuple[str, ...], args) -> tuple[float, list]:
    """Wall time and latencies of `clients` clients sending `scans` requests each, their models
    taken in turn."""
    latencies: list[float] = []
    limits = httpx.Limits(max_connections=args.clients)
    async with httpx.AsyncClient(base_url=url, timeout=args.timeout, limits=limits) as client:

        async def one_client(offset: int) -> None:
            for i in range(args.scans):
                model = names[(offset + i) % len(names)]
                start = time.perf_counter()
                answer = await client.post(
                    "/v1/scans", params={"model": model}, content=body, headers=OCTET
                )
                answer.raise_for_status()
                latencies.append(time.perf_counter() - start)

        for name in names:
            for _ in range(2):
                answer = await client.post(
                    "/v1/scans", params={"model": name}, content=body, headers=OCTET
                )
                answer.raise_for_status()
        start = time.perf_counter()
        await asyncio.gather(*(one_client(c) for c in range(args.clients)))
        return time.perf_counter() - start, latencies


def throughput(folder: Path, weights: dict[str, Path], body: bytes, args) -> list[dict]:
    """Scans/s and latency percentiles with 1, 2 and 3 models, all loaded."""
    rows = []
    for count in (1, 2, 3):
        names = NAMES[:count]
        gw = launch(folder, weights, names, count, args)
        try:
            wall, latencies = asyncio.run(round_robin(gw.url, body, names, args))
        finally:
            gw.stop()
        rows.append(
            {
                "models": count,
                "scans_per_s": len(latencies) / wall,
                "p50_ms": 1000 * float(np.percentile(latencies, 50)),
                "p99_ms": 1000 * float(np.percentile(latencies, 99)),
            }
        )
    return rows


def resident(
    folder: Path, weights: dict[str, Path], names: tuple[str, ...], max_loaded: int, body, args
) -> dict:
    """A gateway's VmRSS (MiB) after start and after `rounds` x 8 requests taken in turn over its
    models, and the models loaded then."""
    gw = launch(folder, weights, names, max_loaded, args, RELEASE[:2])
    try:
        started = rss_mib(gw.proc.pid)
        with httpx.Client(base_url=gw.url, timeout=args.timeout) as client:
            for i in range(args.rounds * len(EIGHT)):
                timed(client, body, names[i % len(names)])
            models = client.get("/v1/models").json()["models"]
            after = rss_mib(gw.proc.pid)
    finally:
        gw.stop()
    return {"start": started, "after": after, "loaded": sum(m["loaded"] for m in models)}


def memory(folder: Path, body: bytes, args) -> list[tuple[str, dict]]:
    """VmRSS of one model, of eight with `--max-loaded 1` and of eight with `--max-loaded 8`."""
    folder = folder / "memory"
    folder.mkdir()
    weights = checkpoints(folder, EIGHT, *RELEASE)
    size = weights[EIGHT[0]].stat().st_size / 2**20
    print(f"memory: rangeret-cir of the release's shape, {size:.1f} MiB per checkpoint")
    cases = [("1 model", EIGHT[:1], 1), ("8 models, --max-loaded 1", EIGHT, 1)]
    cases.append(("8 models, --max-loaded 8", EIGHT, 8))
    return [
        (label, resident(folder, weights, names, max_loaded, body, args))
        for label, names, max_loaded in cases
    ]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--height", type=int, default=32)
    p.add_argument("--width", type=int, default=512)
    p.add_argument("--blocks", type=int, default=2, help="retention blocks of each network")
    p.add_argument("--every", type=int, default=4, help="keep every N-th point of the real scan")
    p.add_argument("--switches", type=int, default=5, help="alternations measured")
    p.add_argument("--clients", type=int, default=6)
    p.add_argument("--scans", type=int, default=8, help="requests per client")
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    p.add_argument("--timeout", type=float, default=300.0)
    p.add_argument(
        "--rounds", type=int, default=2, help="rounds over the eight models before memory is read"
    )
    p.add_argument("--sections", nargs="+", choices=SECTIONS, default=list(SECTIONS))
    args = p.parse_args()
    require_real_scan()
    body = read_scan(REAL_SCAN)[:: args.every].tobytes()
    print(f"{len(body) // 16:,} points per scan, {args.device}")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        weights = checkpoints(folder, NAMES, args.height, args.width, args.blocks)
        size = weights["one"].stat().st_size / 2**20
        if {"switch", "throughput"} & set(args.sections):
            print(
                f"rangeret-cir, {args.blocks} blocks, {size:.1f} MiB per checkpoint, "
                f"{args.height}x{args.width}"
            )
        if "switch" in args.sections:
            report_switch_cost(switch_cost(folder, weights, body, args), args)
        if "throughput" in args.sections:
            report_throughput(throughput(folder, weights, body, args), args)
        if "memory" in args.sections:
            report_memory(memory(folder, body, args), args)


def report_switch_cost(cost: dict[str, float], args) -> None:
    """The switch cost's line."""
    print(
        f"--max-loaded 1, median of {args.switches * 2}: a request on the loaded model "
        f"{cost['stay_s'] * 1000:.0f} ms, one that switches models "
        f"{cost['switch_s'] * 1000:.0f} ms (x{cost['switch_s'] / cost['stay_s']:.1f}); "
        f"a switch costs {(cost['switch_s'] - cost['stay_s']) * 1000:.0f} ms"
    )


def report_throughput(rows: list[dict], args) -> None:
    """The throughput table."""
    base = rows[0]["scans_per_s"]
    print(f"{args.clients} clients x {args.scans} requests, models taken in turn, all loaded:")
    print("models  scans/s  ratio  p50 ms  p99 ms")
    for row in rows:
        print(
            f"{row['models']:>6}  {row['scans_per_s']:7.2f}  {row['scans_per_s'] / base:5.2f}  "
            f"{row['p50_ms']:6.0f}  {row['p99_ms']:6.0f}"
        )


def report_memory(rows: list[tuple[str, dict]], args) -> None:
    """The memory table: VmRSS after start and after the requests, beside the one-model one."""
    print(f"resident memory (VmRSS) after {args.rounds * len(EIGHT)} requests taken in turn:")
    print("gateway                    loaded  start MiB  after MiB  vs 1 model")
    base = rows[0][1]["after"]
    for label, row in rows:
        print(
            f"{label:<25}  {row['loaded']:>6}  {row['start']:9.0f}  {row['after']:9.0f}  "
            f"{row['after'] - base:+9.0f}"
        )


if __name__ == "__main__":
    main()
