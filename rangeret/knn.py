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
dataset's unlabeled class (`unprojected`). Which of several equal distances takes the k-th place is arbitrary in the published
code; here the point's own pixel (distance 0) always takes one, and of the neighbours tied at the
k-th place those that come first in the window (row-major) are kept.

How it runs: points are processed in chunks laid out as (neighbour, point), so every step is an
elementwise operation over a contiguous row of points. The k - 1 smallest neighbour distances of
each point (plus one more, to see ties) are found by an insertion network made of `clamp` calls:
a sorted list is updated with one neighbour at a time, for all points at once, which is much
faster than a per-point `topk`. The neighbours at or below the resulting threshold are compacted
into k - 1 slots by a second network over small integer keys, and their classes are counted.
Memory is O(S^2 * (H * W + chunk_size)) whatever the number of points; everything stays on the
device of the input tensors.

Threads: on the CPU this issues about 150 small operations per chunk, each parallelised over
torch's intra-op threads. That is the fastest on cores of its own (about 35 ms for 123k points,
k = S = 7, 2 cores; 53 ms on one thread), but when another process keeps the same cores busy
with its own spinning OpenMP threads, every operation can wait for a time slice and a call may
take seconds. A caller that shares its cores (a pipeline running the network beside it) should
run it with `torch.set_num_threads(1)`, or give it cores of its own.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["CPU_CHUNK_SIZE", "CUDA_CHUNK_SIZE", "gaussian_kernel", "refine"]

#: Points per chunk on the CPU: large enough to keep per-call overhead small, small enough for
#: the network's rows to stay in cache (about 20 MB of working memory at S = 7).
CPU_CHUNK_SIZE = 65_536
#: Points per chunk on other devices, where fewer and larger kernels pay off (about 80 MB at S = 7).
CUDA_CHUNK_SIZE = 262_144

ArrayLike = np.ndarray | torch.Tensor


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
def refine(
    proj_range: ArrayLike,
    unproj_range: ArrayLike,
    proj_argmax: ArrayLike,
    proj_x: ArrayLike,
    proj_y: ArrayLike,
    k: int = 7,
    search: int = 7,
    sigma: float = 1.0,
    cutoff: float = 1.0,
    num_classes: int = 20,
    *,
    votes_from: int = 1,
    unprojected: int = 0,
    chunk_size: int | None = None,
) -> ArrayLike:
    """Per-point classes from a per-pixel argmax by a kNN vote in range.

    proj_range: (H, W) range of each pixel, -1 where empty. unproj_range: (N,) range of each
    point. proj_argmax: (H, W) integer classes in [0, num_classes). proj_x, proj_y: (N,) column and
    row of each point, proj_x == -1 for points that were not projected (they get `unprojected`).
    k neighbours among the search x search window; Gaussian weight `sigma`; neighbours farther than
    `cutoff` do not vote (no cutoff when it is <= 0). chunk_size bounds the points processed at
    once (default: CPU_CHUNK_SIZE on the CPU, CUDA_CHUNK_SIZE elsewhere). Classes votes_from..C-1
    vote; a point without a vote gets class `votes_from`.

    Returns (N,) int64 classes: a numpy array when every input is a numpy array, otherwise a
    torch tensor on the device of the tensor inputs (numpy inputs are moved there).
    Ranges are compared in float32, as the published code does.
    """
    _check_parameters(k, search, sigma, cutoff, num_classes, chunk_size)
    for name, value in (("votes_from", votes_from), ("unprojected", unprojected)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer):
            raise ValueError(f"{name} must be a class id, got {value!r}")
        if not 0 <= value < num_classes:
            raise ValueError(f"{name} must be a class id in 0..{num_classes - 1}, got {value}")
    as_numpy, device = _output_kind(proj_range, unproj_range, proj_argmax, proj_x, proj_y)
    image, ranges, classes, cols, rows = (
        _to_tensor(proj_range, "proj_range", device),
        _to_tensor(unproj_range, "unproj_range", device),
        _to_tensor(proj_argmax, "proj_argmax", device),
        _to_tensor(proj_x, "proj_x", device),
        _to_tensor(proj_y, "proj_y", device),
    )
    _check_inputs(image, ranges, classes, cols, rows, num_classes)
    if chunk_size is None:
        chunk_size = CPU_CHUNK_SIZE if device.type == "cpu" else CUDA_CHUNK_SIZE

    total = ranges.shape[0]
    projected = cols >= 0
    everything = bool(projected.all())
    if not everything:
        points = torch.nonzero(projected).squeeze(1)
        ranges, cols, rows = ranges[points], cols[points], rows[points]
    result = torch.empty(ranges.shape[0], dtype=torch.int64, device=device)
    if ranges.shape[0]:
        window = _Window(image, classes, search, sigma, num_classes, votes_from)
        for start in range(0, ranges.shape[0], chunk_size):
            stop = start + chunk_size
            result[start:stop] = window.vote(
                ranges[start:stop], cols[start:stop], rows[start:stop], k, cutoff
            )
    if not everything:
        result = torch.full((total,), unprojected, dtype=torch.int64, device=device).index_copy_(
            0, points, result
        )
    return result.cpu().numpy() if as_numpy else result


class _Window:
    """The S x S neighbourhood of every pixel of one range image, ready to be gathered per point.

    `ranges` is a (S^2 - 1, H * W) table of neighbour ranges (centre left out, empty pixels at
    +inf, zero padding outside the image); `codes` the matching neighbour class codes (see
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
        height, width = image.shape
        pad = search // 2
        device = image.device
        self.width = width
        self.pixels = height * width
        self.num_classes = num_classes
        self.votes_from = votes_from

        offsets = [
            (dy, dx) for dy in range(search) for dx in range(search) if (dy, dx) != (pad, pad)
        ]
        self.size = len(offsets)
        weights = (1.0 - gaussian_kernel(search, sigma)).reshape(-1)
        centre = search * search // 2
        weights = torch.cat([weights[:centre], weights[centre + 1 :]])
        self.weights = weights.to(device)[:, None]

        far = torch.where(image < 0, torch.full_like(image, float("inf")), image)
        far = F.pad(far, (pad, pad, pad, pad))
        self.ranges = _shifted(far, offsets, height, width)

        # Compaction keys: j for neighbour j when selected, size + j when it is tied at the
        # threshold, `empty` when it is not selected. Rows of `codes` follow the keys; a code is
        # C + 1 - class for a class that votes, 0 for one that does not and for `empty`; the
        # padding holds class 0's code (see `_majority`).
        self.empty = 2 * self.size
        self.key_dtype = _small_int_dtype(self.empty)
        self.positions = torch.arange(self.size, device=device, dtype=self.key_dtype)[:, None]
        self.to_empty = self.empty - self.positions
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
        self, ranges: torch.Tensor, cols: torch.Tensor, rows: torch.Tensor, k: int, cutoff: float
    ) -> torch.Tensor:
        """Classes of one chunk of projected points."""
        pixels = rows * self.width + cols
        voters = [self.centre_codes.index_select(0, pixels)[None]]
        wanted = k - 1  # neighbours besides the centre, whose distance is 0
        if wanted and self.size:
            dist = self.ranges.index_select(1, pixels)
            dist.sub_(ranges).abs_().mul_(self.weights)
            keys = self._keys(dist, wanted, cutoff)
            slots = keys if wanted >= self.size else _smallest(keys, wanted, self.empty)
            index = slots.to(self.index_dtype).mul_(self.pixels).add_(pixels.to(self.index_dtype))
            voters.append(self.codes.index_select(0, index.reshape(-1)).reshape(slots.shape))
        return _majority(torch.cat(voters), self.num_classes, self.votes_from)

    def _keys(self, dist: torch.Tensor, wanted: int, cutoff: float) -> torch.Tensor:
        """(size, n) compaction keys: which neighbours are among the `wanted` nearest and valid."""
        if wanted >= self.size:
            if cutoff <= 0:
                return self.positions.expand_as(dist).clone()
            return self._select(dist, torch.full_like(dist[0], cutoff))
        nearest = _smallest(dist, wanted + 1, float("inf"))
        kth, after = nearest[wanted - 1], nearest[wanted]
        keys = self._select(dist, kth.clamp(max=cutoff) if cutoff > 0 else kth)
        tied = kth == after
        if cutoff > 0:
            tied &= kth <= cutoff
        tied_points = torch.nonzero(tied).squeeze(1)
        if tied_points.numel():
            # More than `wanted` neighbours at or below the threshold: all strictly nearer ones
            # go first, then the tied ones in window order.
            sub = dist[:, tied_points]
            sub_kth = kth[tied_points]
            empty = torch.tensor(self.empty, dtype=self.key_dtype, device=dist.device)
            keys[:, tied_points] = torch.where(
                sub < sub_kth,
                self.positions,
                torch.where(sub == sub_kth, self.positions + self.size, empty),
            )
        return keys

    def _select(self, dist: torch.Tensor, limit: torch.Tensor) -> torch.Tensor:
        """Keys j where dist <= limit and `empty` elsewhere (as j + (empty - j) * [dist > limit])."""
        beyond = torch.gt(dist, limit)
        keys = (
            beyond.view(torch.uint8) if self.key_dtype == torch.uint8 else beyond.to(self.key_dtype)
        )
        return keys.mul_(self.to_empty).add_(self.positions)


def _shifted(
    padded: torch.Tensor, offsets: list[tuple[int, int]], height: int, width: int
) -> torch.Tensor:
    """(len(offsets), H * W): row j is the padded image seen from every pixel at offset j."""
    if not offsets:
        return padded.new_empty(0, height * width)
    return torch.stack([padded[dy : dy + height, dx : dx + width] for dy, dx in offsets]).reshape(
        len(offsets), height * width
    )


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


def _check_parameters(
    k: int, search: int, sigma: float, cutoff: float, num_classes: int, chunk_size: int | None
) -> None:
    """Raise ValueError, naming the argument, for parameters the method cannot use."""
    if isinstance(search, bool) or not isinstance(search, int | np.integer):
        raise ValueError(f"search must be an odd integer >= 1, got {search!r}")
    if search < 1 or search % 2 == 0:
        raise ValueError(f"search must be an odd integer >= 1, got {search}")
    if isinstance(k, bool) or not isinstance(k, int | np.integer) or k < 1:
        raise ValueError(f"k must be an integer >= 1, got {k!r}")
    if k > search * search:
        raise ValueError(f"k must be at most search**2 = {search * search}, got {k}")
    if not sigma > 0:
        raise ValueError(f"sigma must be > 0, got {sigma!r}")
    if math.isnan(cutoff):
        raise ValueError("cutoff must be a number (<= 0 for no cutoff), got NaN")
    if isinstance(num_classes, bool) or not isinstance(num_classes, int | np.integer):
        raise ValueError(f"num_classes must be an integer >= 2, got {num_classes!r}")
    if num_classes < 2:
        raise ValueError(f"num_classes must be an integer >= 2, got {num_classes}")
    if chunk_size is not None and (
        isinstance(chunk_size, bool)
        or not isinstance(chunk_size, int | np.integer)
        or chunk_size < 1
    ):
        raise ValueError(f"chunk_size must be a positive integer, got {chunk_size!r}")


def _output_kind(*inputs: object) -> tuple[bool, torch.device]:
    """Whether the result is numpy (no tensor among the inputs) and the device to compute on."""
    devices = {x.device for x in inputs if isinstance(x, torch.Tensor)}
    if len(devices) > 1:
        names = ", ".join(sorted(str(d) for d in devices))
        raise ValueError(f"the input tensors are on different devices ({names}); move them to one")
    if not devices:
        return True, torch.device("cpu")
    return False, devices.pop()


def _to_tensor(value: object, name: str, device: torch.device) -> torch.Tensor:
    """`value` as a tensor on `device`: floats as float32 (the published precision), ints as int64."""
    if isinstance(value, torch.Tensor):
        kind = "f" if value.is_floating_point() else "b" if value.dtype == torch.bool else "i"
        if value.is_complex():
            kind = "c"
    else:
        value = np.asarray(value)
        kind = value.dtype.kind
    if kind not in "fiu":
        raise ValueError(f"{name} must hold real numbers, got dtype {value.dtype}")
    if kind == "f" and name in ("proj_argmax", "proj_x", "proj_y"):
        raise ValueError(f"{name} must hold integers, got dtype {value.dtype}")
    dtype = torch.float32 if kind == "f" else torch.int64
    if isinstance(value, np.ndarray):
        array = np.ascontiguousarray(value, dtype=np.float32 if kind == "f" else np.int64)
        value = torch.from_numpy(array if array.flags.writeable else array.copy())
    return value.to(device=device, dtype=dtype)


def _check_inputs(
    image: torch.Tensor,
    ranges: torch.Tensor,
    classes: torch.Tensor,
    cols: torch.Tensor,
    rows: torch.Tensor,
    num_classes: int,
) -> None:
    """Raise ValueError, naming the argument, for shapes or values that do not fit together."""
    if image.dim() != 2:
        raise ValueError(f"proj_range must be (H, W), got shape {tuple(image.shape)}")
    if classes.shape != image.shape:
        raise ValueError(
            f"proj_argmax must have the shape of proj_range {tuple(image.shape)}, "
            f"got {tuple(classes.shape)}"
        )
    if ranges.dim() != 1:
        raise ValueError(f"unproj_range must be (N,), got shape {tuple(ranges.shape)}")
    if not ranges.shape == cols.shape == rows.shape:
        raise ValueError(
            "unproj_range, proj_x and proj_y must have the same shape (N,), got "
            f"{tuple(ranges.shape)}, {tuple(cols.shape)} and {tuple(rows.shape)}"
        )
    if classes.numel():
        low, high = int(classes.min()), int(classes.max())
        if low < 0 or high >= num_classes:
            raise ValueError(
                f"proj_argmax must hold classes in [0, {num_classes}), got values in [{low}, {high}]"
            )
    if ranges.numel() == 0:
        return
    height, width = image.shape
    projected = cols >= 0
    if int(cols.min()) < -1:
        raise ValueError("proj_x must be -1 (not projected) or a column in [0, W)")
    if bool(projected.any()):
        if int(cols.max()) >= width:
            raise ValueError(f"proj_x must be below the image width {width}, got {int(cols.max())}")
        inside = rows[projected]
        if int(inside.min()) < 0 or int(inside.max()) >= height:
            raise ValueError(
                f"proj_y must be in [0, {height}) for projected points, "
                f"got values in [{int(inside.min())}, {int(inside.max())}]"
            )
