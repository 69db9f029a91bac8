"""kNN refinement time on the real scan's test vector (123,389 points, 64 x 1024), against the
published RangeNet++ post-processing timed in the same run.

Run by hand: `python benchmarks/bench_knn.py`. For the release parameters (k 7, search 7) and
RangeNet++'s (k 5, search 5), on the CPU with torch's threads and with one thread, and on CUDA
when there is one: the median time of `refine` and of the published algorithm (a faithful copy
below, `published_knn`), timed in interleaved rounds, their ratio (target: 10x) and how many labels
each gives equal to the published output stored with the test vector. Then a batch of 8 copies of
the scan refined in one `refine_batch` call as `Predictor` makes it (projections as numpy arrays,
the argmax a tensor on the device), per batch and per scan. Timings need the cores to themselves.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from collections.abc import Callable

import numpy as np
import torch
import torch.nn.functional as F
from _common import DATA, median_time

from rangeret.inference.knn import refine_batch
from rangeret.inference.settings import DEFAULT_KNN
from rangeret.knn import refine

FIXTURE = DATA / "knn-semantickitti-scan.npz"
INPUTS = ("proj_range", "unproj_range", "proj_argmax", "proj_x", "proj_y")
TARGET_RATIO = 10.0
PARAMETERS = [(7, 7), (5, 5)]
ROUNDS = 21
BATCH = 8


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--rounds", type=int, default=ROUNDS, help=f"interleaved rounds (default {ROUNDS})"
    )
    rounds = parser.parse_args().rounds
    if not FIXTURE.exists():
        sys.exit(f"{FIXTURE} is missing: the repository carries it in tests/data")
    with np.load(FIXTURE) as data:
        arrays = {name: data[name] for name in INPUTS}
        expected = {(k, s): data[f"expected_knn{k}_search{s}"] for k, s in PARAMETERS}
    points = len(arrays["unproj_range"])
    print(
        f"kNN refinement of one scan ({points:,} points, 64 x 1024), medians of {rounds} "
        f"interleaved rounds; target: {TARGET_RATIO:.0f}x the published code:"
    )
    threads = torch.get_num_threads()
    runs = [("cpu", threads)] + ([("cpu", 1)] if threads > 1 else [])
    runs += [("cuda", threads)] if torch.cuda.is_available() else []
    for device, run_threads in runs:
        torch.set_num_threads(run_threads)
        label = f"{device} ({run_threads} thread{'s' if run_threads > 1 else ''})"
        tensors = [torch.from_numpy(arrays[name]).to(device) for name in INPUTS]
        for k, search in PARAMETERS:
            ours, published, times = time_pair(tensors, k, search, rounds)
            ratio = times["published"] / times["ours"]
            print(
                f"  {label:15} k {k} search {search}: {1e3 * times['ours']:7.2f} ms  "
                f"({points / times['ours'] / 1e6:5.2f} M points/s), published "
                f"{1e3 * times['published']:7.2f} ms: {ratio:5.1f}x "
                f"({'meets' if ratio >= TARGET_RATIO else 'misses'} the {TARGET_RATIO:.0f}x "
                f"target; per-round ratio median {times['ratio']:.1f}x)"
            )
            print(
                f"  {'':15} equal to the stored published output: ours "
                f"{100 * (ours == expected[k, search]).mean():.3f} %, published code "
                f"{100 * (published == expected[k, search]).mean():.3f} %"
            )
        result, seconds = time_batch(arrays, device)
        agree = (result == np.tile(expected[7, 7], BATCH)).mean()
        print(
            f"  {label:15} k 7 search 7, batch of {BATCH}: {1e3 * seconds:7.2f} ms  "
            f"{1e3 * seconds / BATCH:7.2f} ms per scan  "
            f"{BATCH * points / seconds / 1e6:6.2f} M points/s  "
            f"({100 * agree:.3f} % equal to the published output)"
        )


def time_pair(
    tensors: list[torch.Tensor], k: int, search: int, rounds: int
) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
    """Both results and the medians over interleaved rounds of `refine` and of the published
    algorithm (seconds, and the median of the per-round ratios), CUDA synchronised."""

    def ours() -> torch.Tensor:
        return refine(*tensors, k=k, search=search, sigma=1.0, cutoff=1.0)

    def published() -> torch.Tensor:
        return published_knn(*tensors, knn=k, search=search, sigma=1.0, cutoff=1.0, nclasses=20)

    runs: dict[str, Callable[[], torch.Tensor]] = {"ours": ours, "published": published}
    results = {name: run().cpu().numpy() for name, run in runs.items()}
    samples: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(rounds):
        for name, run in runs.items():
            samples[name].append(timed(run))
    times = {name: statistics.median(values) for name, values in samples.items()}
    ratios = [p / o for p, o in zip(samples["published"], samples["ours"], strict=True)]
    times["ratio"] = statistics.median(ratios)
    return results["ours"], results["published"], times


def timed(run: Callable[[], torch.Tensor]) -> float:
    """Seconds of one call, the device's work included."""
    start = time.perf_counter()
    out = run()
    if out.device.type == "cuda":
        torch.cuda.synchronize()
    return time.perf_counter() - start


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


def published_gaussian_kernel(kernel_size: int, sigma: float) -> torch.Tensor:
    """The published code's (S, S) Gaussian: float32 throughout, normalised to sum 1."""
    x_coord = torch.arange(kernel_size)
    x_grid = x_coord.repeat(kernel_size).view(kernel_size, kernel_size)
    y_grid = x_grid.t()
    xy_grid = torch.stack([x_grid, y_grid], dim=-1).float()
    mean = (kernel_size - 1) / 2.0
    variance = sigma**2.0
    kernel = (1.0 / (2.0 * math.pi * variance)) * torch.exp(
        -torch.sum((xy_grid - mean) ** 2.0, dim=-1) / (2 * variance)
    )
    kernel = kernel / torch.sum(kernel)
    return kernel.view(kernel_size, kernel_size)


def published_knn(
    proj_range: torch.Tensor,
    unproj_range: torch.Tensor,
    proj_argmax: torch.Tensor,
    px: torch.Tensor,
    py: torch.Tensor,
    *,
    knn: int,
    search: int,
    sigma: float,
    cutoff: float,
    nclasses: int,
) -> torch.Tensor:
    """RangeNet++'s kNN post-processing, step for step as published (one scan, every point
    projected): unfold the S x S windows, `topk` the k nearest in weighted range, vote."""
    device = proj_range.device
    _, width = proj_range.shape
    points = unproj_range.shape
    pad = int((search - 1) / 2)
    proj_unfold_k_rang = F.unfold(
        proj_range[None, None, ...], kernel_size=(search, search), padding=(pad, pad)
    )
    idx_list = py * width + px
    unproj_unfold_k_rang = proj_unfold_k_rang[:, :, idx_list]
    unproj_unfold_k_rang[unproj_unfold_k_rang < 0] = float("inf")
    center = int(((search * search) - 1) / 2)
    unproj_unfold_k_rang[:, center, :] = unproj_range
    k2_distances = torch.abs(unproj_unfold_k_rang - unproj_range)
    inv_gauss_k = (1 - published_gaussian_kernel(search, sigma)).view(1, -1, 1)
    inv_gauss_k = inv_gauss_k.to(device).type(proj_range.type())
    k2_distances = k2_distances * inv_gauss_k
    _, knn_idx = k2_distances.topk(knn, dim=1, largest=False, sorted=False)
    proj_unfold_1_argmax = F.unfold(
        proj_argmax[None, None, ...].float(), kernel_size=(search, search), padding=(pad, pad)
    ).long()
    unproj_unfold_1_argmax = proj_unfold_1_argmax[:, :, idx_list]
    knn_argmax = torch.gather(input=unproj_unfold_1_argmax, dim=1, index=knn_idx)
    if cutoff > 0:
        knn_distances = torch.gather(input=k2_distances, dim=1, index=knn_idx)
        knn_invalid_idx = knn_distances > cutoff
        knn_argmax[knn_invalid_idx] = nclasses
    knn_argmax_onehot = torch.zeros((1, nclasses + 1, points[0]), device=device).type(
        proj_range.type()
    )
    ones = torch.ones_like(knn_argmax).type(proj_range.type())
    knn_argmax_onehot = knn_argmax_onehot.scatter_add_(1, knn_argmax, ones)
    knn_argmax_out = knn_argmax_onehot[:, 1:-1].argmax(dim=1) + 1
    return knn_argmax_out.view(points)


if __name__ == "__main__":
    main()
