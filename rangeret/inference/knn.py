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

On the CPU a compiled vote (`knn_native`, `csrc/knn_vote.c`) runs the same rule one point per
vector lane, split over torch's intra-op threads; it is several times faster than any sequence of
torch operations, whose every step goes through memory. Elsewhere, and on the CPU where the
library was not built or a scan holds ranges that are not numbers, the exact rule runs in torch
(`knn_rule.Window`): everything stays on the device and the work never waits for its results (no
data-dependent shapes; the host arrays are copied from pinned memory on CUDA). Both give the same
labels, ties included.

Threads: on the CPU each scan's points are split between torch's intra-op threads. That is the
fastest on cores of their own (`benchmarks/bench_knn.py` measures it on one thread and on all);
a caller that shares its cores (a pipeline running the network beside it) should run it with
`torch.set_num_threads(1)`, or give it cores of its own.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from rangeret.inference.knn_native import vote_on_cpu
from rangeret.inference.knn_rule import Window, gaussian_kernel, to_device
from rangeret.inference.settings import KnnSettings

__all__ = [
    "CHUNK_SIZE",
    "flat_pixels",
    "gaussian_kernel",
    "refine_batch",
    "to_device",
]

#: Points the exact rule takes at once in torch, where fewer and larger kernels pay off (about
#: 80 MB at S = 7).
CHUNK_SIZE = 262_144


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
    the exact rule in torch takes at once (default CHUNK_SIZE; the compiled vote streams). The
    device never waits on the host: the only wait is the caller's read of the result.
    """
    device = argmax.device
    ends = np.cumsum([0, *(len(x) for x in proj_x)]).tolist()
    if device.type != "cpu":
        return _exact(
            argmax,
            proj_range,
            unproj_range,
            proj_x,
            proj_y,
            knn,
            num_classes,
            votes_from,
            unprojected,
            chunk_size,
        )
    # numpy, not torch: a torch operation here would leave its OpenMP threads spinning on the
    # cores the vote's threads are about to use
    result = torch.from_numpy(np.full(ends[-1], unprojected, dtype=np.int64))
    classes = argmax.numpy()
    for scan in range(argmax.shape[0]):
        if ends[scan] == ends[scan + 1]:
            continue
        part = slice(ends[scan], ends[scan + 1])
        arrays = (proj_range[scan], unproj_range[scan], proj_x[scan], proj_y[scan])
        image, ranges, x, y = (np.asarray(a) for a in arrays)
        done = vote_on_cpu(
            result[part].numpy(), classes[scan], image, ranges, x, y, knn, num_classes, votes_from
        )
        if not done:
            result[part] = _exact(
                argmax[scan : scan + 1],
                [image],
                [ranges],
                [x],
                [y],
                knn,
                num_classes,
                votes_from,
                unprojected,
                chunk_size,
            )
    return result


def _exact(
    argmax: torch.Tensor,
    proj_range: Sequence[np.ndarray],
    unproj_range: Sequence[np.ndarray],
    proj_x: Sequence[np.ndarray],
    proj_y: Sequence[np.ndarray],
    knn: KnnSettings,
    num_classes: int,
    votes_from: int,
    unprojected: int,
    chunk_size: int | None,
) -> torch.Tensor:
    """`refine_batch` by the exact rule in torch, on argmax's device, `chunk_size` points at a
    time (default CHUNK_SIZE)."""
    device = argmax.device
    _, height, width = argmax.shape
    total = sum(len(x) for x in proj_x)
    chunk_size = chunk_size or CHUNK_SIZE
    pinned = device.type == "cuda"
    pixels = flat_pixels(proj_x, proj_y, height, width, device)
    images = to_device([r[None] for r in proj_range], torch.float32, device, pinned=pinned)
    ranges = to_device(unproj_range, torch.float32, device, pinned=pinned)
    window = Window.of_images(
        images, argmax.to(torch.int64), knn.search, knn.sigma, num_classes, votes_from
    )
    result = torch.empty(total, dtype=torch.int64, device=device)
    for start in range(0, total, chunk_size):
        stop = min(start + chunk_size, total)
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
