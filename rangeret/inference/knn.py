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
is the checked entry point for arrays from elsewhere). The scans' points are processed in chunks
of their concatenation laid out as (neighbour, point), so every step is an elementwise operation
over a contiguous row of points. The k - 1 smallest neighbour distances of each point are found
by an insertion network made of `clamp` calls: a sorted list is updated with one neighbour at a
time, for all points at once, which is much faster than a per-point `topk`. The neighbours below
the resulting threshold, then those at it, are compacted into k - 1 slots by a second network over
small integer keys, and their classes are counted. On the CPU a few scans share one neighbourhood
table at a time (see CPU_WINDOW_PIXELS); memory is O(S^2 * (B * H * W + chunk_size)) whatever the
number of points. Everything stays on the argmax's device and the work never waits for the
device's results (no data-dependent shapes): the host arrays are copied from pinned memory on CUDA.

Threads: on the CPU this issues about 150 small operations per chunk, each parallelised over
torch's intra-op threads. That is the fastest on cores of its own (`benchmarks/bench_knn.py`
measures it on one thread and on all), but when another process keeps the same cores busy
with its own spinning OpenMP threads, every operation can wait for a time slice and a call may
take seconds. A caller that shares its cores (a pipeline running the network beside it) should
run it with `torch.set_num_threads(1)`, or give it cores of its own.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from rangeret.inference.settings import KnnSettings

__all__ = [
    "CPU_CHUNK_SIZE",
    "CPU_WINDOW_PIXELS",
    "CUDA_CHUNK_SIZE",
    "flat_pixels",
    "gaussian_kernel",
    "refine_batch",
    "to_device",
]

#: Points per chunk on the CPU: large enough to keep per-call overhead small, small enough for
#: the network's rows to stay in cache (about 20 MB of working memory at S = 7).
CPU_CHUNK_SIZE = 65_536
#: Points per chunk on other devices, where fewer and larger kernels pay off (about 80 MB at S = 7).
CUDA_CHUNK_SIZE = 262_144
#: Most pixels of the scans of a batch that share one neighbourhood table on the CPU (at least one
#: scan): a 64 x 1024 scan's table stays in cache, eight scans' cost about 20 % more per scan.
#: Other devices take the whole batch in one table.
CPU_WINDOW_PIXELS = 65_536


def gaussian_kernel(size: int, sigma: float) -> torch.Tensor:
    """The (size, size) 2D Gaussian centred in the window, normalised to sum 1, as float32.

    Computed in float64 and rounded once, so the weights are the correctly rounded values.
    """
    if size < 1:
        raise ValueError(f"size must be >= 1, got {size}")
    if not sigma > 0:
        raise ValueError(f"sigma must be > 0, got {sigma}")
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    kernel = torch.exp(-(x[:, None] ** 2 + x[None, :] ** 2) / (2.0 * sigma**2))
    return (kernel / kernel.sum()).to(torch.float32)


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
    processed at once (default: CPU_CHUNK_SIZE on the CPU, CUDA_CHUNK_SIZE elsewhere). The device
    never waits on the host: the only wait is the caller's read of the result.
    """
    device = argmax.device
    scans, height, width = argmax.shape
    on_cpu = device.type == "cpu"
    if chunk_size is None:
        chunk_size = CPU_CHUNK_SIZE if on_cpu else CUDA_CHUNK_SIZE
    together = max(1, CPU_WINDOW_PIXELS // (height * width)) if on_cpu else scans
    pinned = device.type == "cuda"
    pixels = flat_pixels(proj_x, proj_y, height, width, device)
    images = to_device([r[None] for r in proj_range], torch.float32, device, pinned=pinned)
    ranges = to_device(unproj_range, torch.float32, device, pinned=pinned)
    classes = argmax.to(torch.int64)
    ends = np.cumsum([0, *(len(x) for x in proj_x)]).tolist()
    result = torch.empty(ends[-1], dtype=torch.int64, device=device)
    for first in range(0, scans, together):
        last = min(first + together, scans)
        if ends[first] == ends[last]:
            continue
        window = _Window(
            images[first:last], classes[first:last], knn.search, knn.sigma, num_classes, votes_from
        )
        offset = first * height * width
        for start in range(ends[first], ends[last], chunk_size):
            stop = min(start + chunk_size, ends[last])
            chunk = pixels[start:stop].sub(offset).clamp_(min=0)
            result[start:stop] = window.vote(ranges[start:stop], chunk, knn.k, knn.cutoff)
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


def to_device(
    parts: Sequence[np.ndarray], dtype: torch.dtype, device: torch.device, *, pinned: bool
) -> torch.Tensor:
    """Host arrays concatenated along their first axis into one `dtype` tensor on `device`.

    With `pinned` (for CUDA) they are gathered in page-locked memory and copied without blocking
    the host, so the copy queues behind the device's work instead of waiting for it.
    """
    shape = (sum(part.shape[0] for part in parts), *parts[0].shape[1:])
    host = torch.empty(shape, dtype=dtype, pin_memory=pinned)
    np.concatenate(parts, out=host.numpy(), casting="unsafe")
    return host.to(device, non_blocking=pinned)


class _Window:
    """The S x S neighbourhood of every pixel of B range images, ready to be gathered per point.

    `ranges` is a (S^2 - 1, B * H * W) table of neighbour ranges (centre left out, empty pixels at
    +inf, zero padding outside each image); `codes` the matching neighbour class codes (see
    `_majority`), flattened, as rows that the compaction keys of `_keys` index directly.
    """

    def __init__(
        self,
        image: torch.Tensor,
        classes: torch.Tensor,
        search: int,
        sigma: float,
        num_classes: int,
        votes_from: int,
    ) -> None:
        scans, height, width = image.shape
        pad = search // 2
        device = image.device
        self.pixels = scans * height * width
        self.num_classes = num_classes
        self.votes_from = votes_from

        offsets = [
            (dy, dx) for dy in range(search) for dx in range(search) if (dy, dx) != (pad, pad)
        ]
        self.size = len(offsets)
        weights = (1.0 - gaussian_kernel(search, sigma)).reshape(-1)
        centre = search * search // 2
        weights = torch.cat([weights[:centre], weights[centre + 1 :]])
        self.weights = to_device(
            [weights.numpy()], torch.float32, device, pinned=device.type == "cuda"
        )[:, None]

        far = torch.where(image < 0, torch.full_like(image, float("inf")), image)
        far = F.pad(far, (pad, pad, pad, pad))
        self.ranges = _shifted(far, offsets, height, width)

        # Compaction keys: j for neighbour j below the threshold, size + j at it, 2 size + j
        # beyond it. Rows of `codes` follow the keys, all keys from `empty` = 2 size on reading
        # its row of zeros; a code is C + 1 - class for a class that votes, 0 for one that does
        # not and for `empty`; the padding holds class 0's code (see `_majority`).
        self.empty = 2 * self.size
        self.key_dtype = _small_int_dtype(3 * self.size)
        self.positions = torch.arange(self.size, device=device, dtype=self.key_dtype)[:, None]
        code_dtype = _small_int_dtype(num_classes + 1)
        inverted = torch.where(classes >= votes_from, num_classes + 1 - classes, 0).to(code_dtype)
        self.centre_codes = inverted.reshape(-1)
        padding = num_classes + 1 if votes_from == 0 else 0
        neighbours = _shifted(
            F.pad(inverted, (pad, pad, pad, pad), value=padding), offsets, height, width
        )
        self.codes = torch.cat(
            [neighbours, neighbours, neighbours.new_zeros(1, self.pixels)]
        ).reshape(-1)
        fits = self.codes.numel() < torch.iinfo(torch.int32).max
        self.index_dtype = torch.int32 if fits else torch.int64

    def vote(
        self, ranges: torch.Tensor, pixels: torch.Tensor, k: int, cutoff: float
    ) -> torch.Tensor:
        """Classes of one chunk of points, given by their range and flat pixel index."""
        voters = [self.centre_codes.index_select(0, pixels)[None]]
        wanted = k - 1  # neighbours besides the centre, whose distance is 0
        if wanted and self.size:
            dist = self.ranges.index_select(1, pixels)
            dist.sub_(ranges).abs_().mul_(self.weights)
            keys = self._keys(dist, wanted, cutoff)
            slots = keys if wanted >= self.size else _smallest(keys, wanted, self.empty)
            slots = slots.clamp(max=self.empty)
            index = slots.to(self.index_dtype).mul_(self.pixels).add_(pixels.to(self.index_dtype))
            voters.append(self.codes.index_select(0, index.reshape(-1)).reshape(slots.shape))
        return _majority(torch.cat(voters), self.num_classes, self.votes_from)

    def _keys(self, dist: torch.Tensor, wanted: int, cutoff: float) -> torch.Tensor:
        """(size, n) compaction keys: which neighbours are among the `wanted` nearest and valid.

        The threshold is the `wanted`-th smallest distance (or the cutoff when lower): fewer than
        `wanted` neighbours lie below it, so the `wanted` smallest keys are all of those, then
        those at it in window order, then (below the cutoff only) neighbours that abstain.
        """
        if wanted >= self.size:
            if cutoff <= 0:
                return self.positions.expand_as(dist).clone()
            return self._select(dist, cutoff)
        kth = _smallest(dist, wanted, float("inf"))[wanted - 1]
        return self._select(dist, kth.clamp(max=cutoff) if cutoff > 0 else kth)

    def _select(self, dist: torch.Tensor, limit: torch.Tensor | float) -> torch.Tensor:
        """Keys j + size * ([dist >= limit] + [dist > limit])."""
        at_or_beyond = torch.ge(dist, limit).view(torch.uint8)
        keys = at_or_beyond.add(torch.gt(dist, limit).view(torch.uint8))
        if self.key_dtype != torch.uint8:
            keys = keys.to(self.key_dtype)
        return keys.mul_(self.size).add_(self.positions)


def _shifted(
    padded: torch.Tensor, offsets: list[tuple[int, int]], height: int, width: int
) -> torch.Tensor:
    """(len(offsets), B * H * W): row j is each padded image seen from every pixel at offset j."""
    if not offsets:
        return padded.new_empty(0, padded.shape[0] * height * width)
    return torch.stack(
        [padded[:, dy : dy + height, dx : dx + width] for dy, dx in offsets]
    ).reshape(len(offsets), -1)


def _small_int_dtype(largest: int) -> torch.dtype:
    """The narrowest of uint8, int16 and int32 that holds 0..largest (narrow rows run faster)."""
    if largest <= torch.iinfo(torch.uint8).max:
        return torch.uint8
    if largest <= torch.iinfo(torch.int16).max:
        return torch.int16
    return torch.int32


def _smallest(values: torch.Tensor, count: int, fill: float | int) -> torch.Tensor:
    """The `count` smallest of each column of (m, n) `values`, ascending, as (count, n).

    An insertion network: `current` holds the smallest so far behind a lower-bound guard row, and
    adding x makes row i min(row i, max(row i-1, x)) = clamp(x, row i-1, row i), all rows in one
    call. Entries that do not exist (count > m) are `fill`.
    """
    n = values.shape[1]
    low = -float("inf") if values.dtype.is_floating_point else torch.iinfo(values.dtype).min
    current = torch.full((count + 1, n), fill, dtype=values.dtype, device=values.device)
    current[0] = low
    spare = current.clone()
    for row in values:
        torch.clamp(row, min=current[:-1], max=current[1:], out=spare[1:])
        current, spare = spare, current
    return current[1:]


def _majority(codes: torch.Tensor, num_classes: int, votes_from: int) -> torch.Tensor:
    """Most frequent class of each column of (k, n) voter `codes` among classes votes_from..C-1.

    A code is C + 1 - class, and 0 for a voter that abstains. Ties go to the lowest class id (the
    highest code); a column without a vote gets class `votes_from`. Each voter scores
    count * (C + 2) + code (0 when it abstains): the largest score is the most votes, then the
    lowest class, and a lookup table turns it back into a class.
    """
    k = codes.shape[0]
    base = num_classes + 2
    top = k * base + num_classes + 1
    dtype = _small_int_dtype(top)
    codes = codes.to(dtype)
    counts = torch.zeros_like(codes)
    for row in codes:
        counts += codes == row
    best = torch.add(codes, counts, alpha=base).masked_fill_(codes == 0, 0).amax(0)
    scores = torch.arange(top + 1, device=codes.device)
    classes = torch.where(scores == 0, votes_from, num_classes + 1 - scores % base)
    return classes.index_select(0, best.to(torch.int32 if top < 2**31 else torch.int64))
