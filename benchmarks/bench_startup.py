"""How long an in-process gateway takes to answer /healthz, and the memory it holds then.

Starts `python -m service` on the bundled demo weights (scans and jobs in its own process) a few
times and reports the median seconds from the process's start to the first 200 of /healthz, its
resident memory then (VmRSS) and its peak (VmHWM). With `--compare DIR`, another checkout of the
project (an older commit, say) is started the same way, alternating with this one in each
round, and the ratios are printed: what a change to loading did, side by side in one run.
Loopback only. Run by hand: `python benchmarks/bench_startup.py [--compare DIR]`.
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
from _common import REPO
from _gateway import START_TIMEOUT_S, free_port


def memory_mib(pid: int) -> dict[str, float]:
    """VmRSS and VmHWM of a process, in MiB."""
    found = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            found[key] = int(value.split()[0]) / 1024
    return found


def start_once(tree: Path, state: Path, device: str) -> dict[str, float]:
    """One gateway of the checkout `tree`: seconds until /healthz answers 200, and its memory."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("RANGERET_")}
    env.update(RANGERET_STATE_DIR=str(state), PYTHONPATH=str(tree))
    port = free_port()
    cmd = [sys.executable, "-m", "service", "--device", device, "--port", str(port)]
    cmd += ["--log-level", "warning"]
    started = time.perf_counter()
    with open(state / "gateway.log", "wb") as log:
        proc = subprocess.Popen(cmd, cwd=tree, env=env, stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + START_TIMEOUT_S
        while time.monotonic() < deadline:
            if proc.poll() is not None:
                sys.exit(f"the gateway of {tree} exited:\n{(state / 'gateway.log').read_text()}")
            try:
                if httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=2).status_code == 200:
                    return {"seconds": time.perf_counter() - started, **memory_mib(proc.pid)}
            except httpx.TransportError:
                pass
            time.sleep(0.05)
        sys.exit(f"the gateway of {tree} did not answer within {START_TIMEOUT_S} s")
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--compare", type=Path, metavar="DIR", help="another checkout to compare")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    args = parser.parse_args()
    trees = {"this": REPO, **({"compared": args.compare.resolve()} if args.compare else {})}
    found: dict[str, list[dict[str, float]]] = {name: [] for name in trees}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            for name, tree in trees.items():
                state = Path(tmp) / f"{name}-{r}"
                state.mkdir()
                found[name].append(start_once(tree, state, args.device))
    print(f"in-process gateway on the demo weights, {args.device}, median of {args.rounds}:")
    medians = {
        name: {k: statistics.median(run[k] for run in runs) for k in runs[0]}
        for name, runs in found.items()
    }
    for name, m in medians.items():
        print(
            f"  {name:<9} ready in {m['seconds']:6.2f} s   RSS {m['VmRSS']:7.1f} MiB   "
            f"peak {m['VmHWM']:7.1f} MiB   ({trees[name]})"
        )
    if args.compare:
        this, other = medians["this"], medians["compared"]
        print(
            "  this / compared: ready time "
            f"{this['seconds'] / other['seconds']:.2f}, RSS {this['VmRSS'] / other['VmRSS']:.2f}, "
            f"peak {this['VmHWM'] / other['VmHWM']:.2f}"
        )


if __name__ == "__main__":
    main()
