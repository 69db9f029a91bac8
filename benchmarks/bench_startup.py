"""How long an in-process gateway takes to answer /healthz and to run its first job, and the
memory it holds then.

Starts `python -m service` (scans and jobs in its own process) on the bundled demo weights, or
with `--release-shape` on weights of the published SemanticKITTI file's shape (rangeret-cir,
8 blocks, 64 x 1024, random values), a few times. Each start reports the median seconds from the
process's start to the first 200 of /healthz and its resident memory then (VmRSS), then runs one
dataset job on one simulated scan and reports the seconds to its end and the memory after it
(VmRSS, and the peak VmHWM). With `--compare DIR`, another checkout of the project (an older
commit, say) is started the same way, alternating with this one in each round, and the ratios
are printed: what a change to loading did, side by side in one run. Loopback only. Run by hand:
`python benchmarks/bench_startup.py [--release-shape] [--compare DIR]`.
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


def start_once(tree: Path, state: Path, data: Path, net: list[str]) -> dict[str, float]:
    """One gateway of the checkout `tree` with the network options `net`: seconds until
    /healthz answers 200 and its memory then, then the seconds and memory of one job on `data`."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("RANGERET_")}
    env.update(RANGERET_STATE_DIR=str(state), RANGERET_DATA_ROOTS=str(data), PYTHONPATH=str(tree))
    port = free_port()
    cmd = [sys.executable, "-m", "service", *net, "--port", str(port), "--log-level", "warning"]
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
                    ready = time.perf_counter() - started
                    return {
                        "ready_s": ready,
                        "ready_rss": memory_mib(proc.pid)["VmRSS"],
                        **run_job(f"http://127.0.0.1:{port}", data, proc.pid),
                    }
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


def run_job(url: str, data: Path, pid: int) -> dict[str, float]:
    """One dataset job of the gateway at `url` on `data`'s sequence 00: seconds to its end and
    the gateway's memory after it."""
    started = time.perf_counter()
    job = httpx.post(f"{url}/v1/jobs", json={"dataset": str(data), "sequences": ["00"]}).json()
    while True:
        state = httpx.get(f"{url}/v1/jobs/{job['id']}").json()["state"]
        if state in ("succeeded", "failed", "cancelled"):
            break
        time.sleep(0.05)
    if state != "succeeded":
        sys.exit(f"the job {job['id']} ended {state}")
    memory = memory_mib(pid)
    return {
        "job_s": time.perf_counter() - started,
        "job_rss": memory["VmRSS"],
        "peak": memory["VmHWM"],
    }


def simulated_scan(root: Path) -> None:
    """One simulated SemanticKITTI scan in `root`'s sequence 00."""
    from rangeret.dataset.profiles import load_profile
    from rangeret.sim import simulate_dataset

    simulate_dataset(root, {"00": 1}, labelled=False, seed=1, profile=load_profile())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--compare", type=Path, metavar="DIR", help="another checkout to compare")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument(
        "--release-shape",
        action="store_true",
        help="weights of the published SemanticKITTI file's shape instead of the demo weights",
    )
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    args = parser.parse_args()
    trees = {"this": REPO, **({"compared": args.compare.resolve()} if args.compare else {})}
    found: dict[str, list[dict[str, float]]] = {name: [] for name in trees}
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "data"
        simulated_scan(data)
        net = ["--device", args.device]
        weights = "the demo weights"
        if args.release_shape:
            import torch

            from rangeret.models import build_model

            path = Path(tmp) / "release-shape.pt"
            torch.save(build_model("rangeret-cir", 64, 1024).state_dict(), path)
            net += ["--checkpoint", str(path)]
            weights = f"release-shaped weights ({path.stat().st_size / 2**20:.1f} MiB)"
        for r in range(args.rounds):
            for name, tree in trees.items():
                state = Path(tmp) / f"{name}-{r}"
                state.mkdir()
                found[name].append(start_once(tree, state, data, net))
    print(f"in-process gateway on {weights}, {args.device}, median of {args.rounds}:")
    medians = {
        name: {k: statistics.median(run[k] for run in runs) for k in runs[0]}
        for name, runs in found.items()
    }
    for name, m in medians.items():
        print(
            f"  {name:<9} ready {m['ready_s']:5.2f} s, RSS {m['ready_rss']:6.1f} MiB; "
            f"first job {m['job_s']:5.2f} s, RSS {m['job_rss']:6.1f} MiB, "
            f"peak {m['peak']:6.1f} MiB  ({trees[name]})"
        )
    if args.compare:
        this, other = medians["this"], medians["compared"]
        ratios = ", ".join(f"{k} {this[k] / other[k]:.2f}" for k in this)
        print(f"  this / compared: {ratios}")


if __name__ == "__main__":
    main()
