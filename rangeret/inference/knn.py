"""kNN refinement: per-pixel predictions back onto every point (RangeNet++ post-processing).

A range image keeps one point per pixel, so the network's per-pixel classes blur across depth
discontinuities when they are copied to all points. For each point this module looks at the
S x S window of pixel ranges around its pixel, with the point's own range in the centre, takes
the k pixels closest in range (|range difference| weighted by 1 - a normalised S x S Gaussian),
drops those farther than `cutoff`, and lets their classes vote.

The behaviour is the published one, detail for detail: outside the image the window is
zero-padded (range 0, class 0, not treated as empty); empty pixels (range < 0) are infinitely far;
the vote is over classes 1..C-1 with ties going to the lowest class id; a point without any vote
gets class 1. Datasets whose class 0 is a real class (PandaSet's car) vote over 0..C-1 instead
(`votes_from=0`; a point without a vote then gets class 0), and points that have no pixel get the
dataset's unlabeled class (`unprojected`). Which of several equal distances takes the k-th place
is arbitrary in the published code; here the point's own pixel (distance 0) always takes one, and
of the neighbours tied at the k-th place those that come first in the window (row-major) are kept.

How it runs: `refine_batch` takes B scans at once, the argmax a tensor on the device and each
scan's projection arrays as a `Projection` holds them (checked there, not here; `rangeret.knn.refine`
is the checked entry point for arrays from elsewhere). Points are laid out as (neighbour, point),
so every step is an elementwise operation over a contiguous row of points. The k - 1 smallest
neighbour distances of each point are found by an insertion network made of `clamp` calls: a
sorted list is updated with one neighbour at a time, for all points at once, which is much faster
than a per-point `topk`.

On devices other than the CPU every point goes through the exact rule (`knn_rule.Window`):
everything stays on the device and the work never waits for its results (no data-dependent
shapes; the host arrays are copied from pinned memory on CUDA). On the CPU, where the host is the
device, a fast path (`knn_cpu`) settles all but about 1 % of the real scan's points (at k 7) from
int16 keys, one network finding the voters and their classes at once, and the exact rule settles
the rest: the same labels, ties included.

Threads: on the CPU the work is a few hundred operations per scan, each parallelised over torch's
intra-op threads (larger pieces and chunks with more threads, so that each operation outweighs
its fork and join). That is the fastest on cores of its own (`benchmarks/bench_knn.py` measures
it on one thread and on all), but when another process keeps the same cores busy with its own
spinning OpenMP threads, every operation can wait for a time slice and a call may take far
longer. A caller that shares its cores (a pipeline running the network beside it) should run it
with `torch.set_num_threads(1)`, or give it cores of its own.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from rangeret.inference.knn_cpu import refine_on_cpu
from rangeret.inference.knn_rule import Window, gaussian_kernel, to_device
from rangeret.inference.settings import KnnSettings

__all__ = [
    "CPU_CHUNK_SIZE",
    "CPU_PIECE_SIZE",
    "CUDA_CHUNK_SIZE",
    "flat_pixels",
    "gaussian_kernel",
    "refine_batch",
    "to_device",
]

#: Most points (or columns of a dense layer) per network call on the CPU, per thread: large
#: enough to keep the per-call overhead small, small enough for the network's int16 rows to stay
#: in a core's cache.
CPU_CHUNK_SIZE = 40_000
#: Points or columns whose float32 distances are worked out at once on the CPU, per thread
#: (about 800 kB at S = 7, so they stay in cache between the few elementwise steps).
CPU_PIECE_SIZE = 4_096
#: Points per chunk on other devices, where fewer and larger kernels pay off (about 80 MB at S = 7).
CUDA_CHUNK_SIZE = 262_144


@torch.no_grad()
def refine_batch(
    argmax: torch.Tensor,
    proj_range: Sequence[np.ndarray],
    unproj_range: Sequence[np.ndarray],
    proj_x: Sequence[np.ndarray],
    proj_y: Sequence[np.ndarray],
    knn: KnnSettings,
    num_classes: int,
    *,
    votes_from: int = 1,
    unprojected: int = 0,
    chunk_size: int | None = None,
) -> torch.Tensor:
    """(N,) int64 classes of B scans' points, concatenated scan by scan, on argmax's device: the
    kNN vote in range over their (B, H, W) per-pixel `argmax` (classes in [0, num_classes)).

    Each scan's arrays are those of its `Projection`: (H, W) proj_range, (N_b,) unproj_range,
    proj_x (-1 for a point without a pixel, which gets `unprojected`) and proj_y. Classes
    votes_from..C-1 vote; a point without a vote gets `votes_from`. chunk_size bounds the points
    (or pixels) processed at once (default: CPU_CHUNK_SIZE per thread on the CPU,
    CUDA_CHUNK_SIZE elsewhere). The device never waits on the host: the only wait is the
    caller's read of the result.
    """
    device = argmax.device
    scans, height, width = argmax.shape
    ends = np.cumsum([0, *(len(x) for x in proj_x)]).tolist()
    if device.type == "cpu":
        result = torch.full((ends[-1],), unprojected, dtype=torch.int64)
        classes = argmax.to(torch.int64).numpy()
        threads = torch.get_num_threads()
        chunk = CPU_CHUNK_SIZE * threads if chunk_size is None else chunk_size
        for scan in range(scans):
            if ends[scan] < ends[scan + 1]:
                refine_on_cpu(
                    result[ends[scan] : ends[scan + 1]].numpy(),
                    classes[scan],
                    np.asarray(proj_range[scan], dtype=np.float32),
                    np.asarray(unproj_range[scan], dtype=np.float32),
                    np.asarray(proj_x[scan]),
                    np.asarray(proj_y[scan]),
                    knn,
                    num_classes,
                    votes_from,
                    chunk,
                    min(CPU_PIECE_SIZE * threads, chunk),
                )
        return result
    if chunk_size is None:
        chunk_size = CUDA_CHUNK_SIZE
    pinned = device.type == "cuda"
    pixels = flat_pixels(proj_x, proj_y, height, width, device)
    images = to_device([r[None] for r in proj_range], torch.float32, device, pinned=pinned)
    ranges = to_device(unproj_range, torch.float32, device, pinned=pinned)
    window = Window.of_images(
        images, argmax.to(torch.int64), knn.search, knn.sigma, num_classes, votes_from
    )
    result = torch.empty(ends[-1], dtype=torch.int64, device=device)
    for start in range(0, ends[-1], chunk_size):
        stop = min(start + chunk_size, ends[-1])
        columns = pixels[start:stop].clamp(min=0)
        result[start:stop] = window.vote(ranges[start:stop], columns, knn.k, knn.cutoff)
    return torch.where(pixels >= 0, result, unprojected)


def flat_pixels(
    proj_x: Sequence[np.ndarray],
    proj_y: Sequence[np.ndarray],
    height: int,
    width: int,
    device: torch.device,
) -> torch.Tensor:
    """(N,) int64 on `device`: each point's pixel among B (H, W) images flattened, -1 for a point
    without one (proj_x == -1); worked out on the host and copied in one go."""
    pixels = []
    for scan, (x, y) in enumerate(zip(proj_x, proj_y, strict=True)):
        x, y = x.astype(np.int64, copy=False), y.astype(np.int64, copy=False)
        pixels.append(np.where(x >= 0, scan * height * width + y * width + x, -1))
    return to_device(pixels, torch.int64, device, pinned=device.type == "cuda")
