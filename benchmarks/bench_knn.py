"""kNN refinement time on the real scan's test vector (123,389 points, 64 x 1024).

Run by hand: `python benchmarks/bench_knn.py`. Prints medians for the release parameters
(k 7, search 7) and RangeNet++'s (k 5, search 5) on the CPU with torch's threads and with one
thread, and on CUDA when there is one, with points/s and the ratio to the published code's
0.22 s on this CPU (target: at most 60 ms); then a batch of 8 copies of the scan refined in one
`refine_batch` call as `Predictor` makes it (projections as numpy arrays, the argmax a tensor on
the device), per batch and per scan. Timings need the cores to themselves.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import torch
from _common import DATA, median_time

from rangeret.inference.knn import refine_batch
from rangeret.inference.settings import DEFAULT_KNN
from rangeret.knn import refine

FIXTURE = DATA / "knn-semantickitti-scan.npz"
INPUTS = ("proj_range", "unproj_range", "proj_argmax", "proj_x", "proj_y")
PUBLISHED_S = 0.22
TARGET_MS = 60.0
PARAMETERS = [(7, 7), (5, 5)]
BATCH = 8


def main() -> None:
    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args()
    if not FIXTURE.exists():
        sys.exit(f"{FIXTURE} is missing: the repository carries it in tests/data")
    with np.load(FIXTURE) as data:
        arrays = {name: data[name] for name in INPUTS}
        expected = {(k, s): data[f"expected_knn{k}_search{s}"] for k, s in PARAMETERS}
    points = len(arrays["unproj_range"])
    print(f"kNN refinement of one scan ({points:,} points, 64 x 1024), median of 21 runs:")
    threads = torch.get_num_threads()
    runs = [("cpu", threads)] + ([("cpu", 1)] if threads > 1 else [])
    runs += [("cuda", threads)] if torch.cuda.is_available() else []
    for device, run_threads in runs:
        torch.set_num_threads(run_threads)
        label = f"{device} ({run_threads} thread{'s' if run_threads > 1 else ''})"
        tensors = [torch.from_numpy(arrays[name]).to(device) for name in INPUTS]
        for k, search in PARAMETERS:
            result, seconds = time_one(tensors, k, search)
            agree = (result == expected[k, search]).mean()
            print(
                f"  {label:15} k {k} search {search}: {1e3 * seconds:7.2f} ms  "
                f"{points / seconds / 1e6:6.2f} M points/s  "
                f"{PUBLISHED_S / seconds:5.1f} x faster than the published {1e3 * PUBLISHED_S:.0f} ms  "
                f"(target {TARGET_MS:.0f} ms; {100 * agree:.3f} % equal to the published output)"
            )
        result, seconds = time_batch(arrays, device)
        agree = (result == np.tile(expected[7, 7], BATCH)).mean()
        print(
            f"  {label:15} k 7 search 7, batch of {BATCH}: {1e3 * seconds:7.2f} ms  "
            f"{1e3 * seconds / BATCH:7.2f} ms per scan  "
            f"{BATCH * points / seconds / 1e6:6.2f} M points/s  "
            f"({100 * agree:.3f} % equal to the published output)"
        )


def time_one(tensors: list[torch.Tensor], k: int, search: int) -> tuple[np.ndarray, float]:
    """The result and the median time of `refine` (synchronising CUDA so its time counts)."""

    def run() -> torch.Tensor:
        out = refine(*tensors, k=k, search=search, sigma=1.0, cutoff=1.0)
        if out.device.type == "cuda":
            torch.cuda.synchronize()
        return out

    return run().cpu().numpy(), median_time(run, repeat=21, warmup=2)


def time_batch(arrays: dict[str, np.ndarray], device: str) -> tuple[np.ndarray, float]:
    """The result and the median time of one `refine_batch` call on BATCH copies of the scan."""
    argmax = torch.from_numpy(np.stack([arrays["proj_argmax"]] * BATCH)).to(device)
    scans = {name: [arrays[name]] * BATCH for name in INPUTS}

    def run() -> torch.Tensor:
        out = refine_batch(
            argmax,
            scans["proj_range"],
            scans["unproj_range"],
            scans["proj_x"],
            scans["proj_y"],
            DEFAULT_KNN,
            num_classes=20,
        )
        return out.cpu()

    return run().numpy(), median_time(run, repeat=5, warmup=1)


if __name__ == "__main__":
    main()
