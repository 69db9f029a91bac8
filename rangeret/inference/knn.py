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
each point are found by an insertion network made of `clamp` calls: a sorted list is updated with
one neighbour at a time, for all points at once, which is much faster than a per-point `topk`.
The neighbours below the resulting threshold, then those at it, are compacted into k - 1 slots by
a second network over small integer keys, and their classes are counted. `refine_batch` does the
same for B scans at once, over their points concatenated (on the CPU, a few scans at a time,
see CPU_WINDOW_PIXELS); memory is O(S^2 * (B * H * W + chunk_size)) whatever the number of
points. Everything stays on the device of the input tensors,
and the work never waits for the device's results (no data-dependent shapes): numpy inputs are
checked on the host and copied from pinned memory on CUDA, tensor inputs are checked on the device
and read once at the end.

Threads: on the CPU this issues about 150 small operations per chunk, each parallelised over
torch's intra-op threads. That is the fastest on cores of its own (about 35 ms for 123k points,
k = S = 7, 2 cores; 53 ms on one thread), but when another process keeps the same cores busy
with its own spinning OpenMP threads, every operation can wait for a time slice and a call may
take seconds. A caller that shares its cores (a pipeline running the network beside it) should
run it with `torch.set_num_threads(1)`, or give it cores of its own.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F

__all__ = [
    "CPU_CHUNK_SIZE",
    "CPU_WINDOW_PIXELS",
    "CUDA_CHUNK_SIZE",
    "gaussian_kernel",
    "pixel_classes",
    "refine",
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

ArrayLike = np.ndarray | torch.Tensor
#: B images: one (B, H, W) array, or B (H, W) arrays.
Images = ArrayLike | Sequence[ArrayLike]
#: B scans' per-point arrays, one (N_b,) array each.
Points = Sequence[ArrayLike]


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
    return refine_batch(
        [proj_range],
        [unproj_range],
        [proj_argmax],
        [proj_x],
        [proj_y],
        k,
        search,
        sigma,
        cutoff,
        num_classes,
        votes_from=votes_from,
        unprojected=unprojected,
        chunk_size=chunk_size,
    )


@torch.no_grad()
def refine_batch(
    proj_range: Images,
    unproj_range: Points,
    proj_argmax: Images,
    proj_x: Points,
    proj_y: Points,
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
    """`refine` of B scans of one resolution in one pass: their results, concatenated scan by scan.

    proj_range and proj_argmax: a (B, H, W) array or B (H, W) arrays; unproj_range, proj_x and
    proj_y: B (N_b,) arrays. The scans' points are processed in chunks of their concatenation, and
    the device waits on the host only for the input checks of tensor inputs (one read, after the work
    is queued); numpy inputs are checked on the host before they are copied.
    """
    _check_parameters(k, search, sigma, cutoff, num_classes, chunk_size)
    for name, value in (("votes_from", votes_from), ("unprojected", unprojected)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer):
            raise ValueError(f"{name} must be a class id, got {value!r}")
        if not 0 <= value < num_classes:
            raise ValueError(f"{name} must be a class id in 0..{num_classes - 1}, got {value}")
    inputs = _Inputs(proj_argmax, proj_x, proj_y, num_classes, proj_range, unproj_range)
    if chunk_size is None:
        chunk_size = CPU_CHUNK_SIZE if inputs.device.type == "cpu" else CUDA_CHUNK_SIZE
    scans, height, width = inputs.image.shape
    together = scans
    if inputs.device.type == "cpu":
        together = max(1, CPU_WINDOW_PIXELS // (height * width))
    ends = np.cumsum([0, *inputs.sizes]).tolist()
    result = torch.empty(ends[-1], dtype=torch.int64, device=inputs.device)
    for first in range(0, scans, together):
        last = min(first + together, scans)
        if ends[first] == ends[last]:
            continue
        window = _Window(
            inputs.image[first:last],
            inputs.classes[first:last],
            search,
            sigma,
            num_classes,
            votes_from,
        )
        offset = first * height * width
        for start in range(ends[first], ends[last], chunk_size):
            stop = min(start + chunk_size, ends[last])
            chunk = inputs.pixels[start:stop].sub(offset).clamp_(min=0)
            result[start:stop] = window.vote(inputs.ranges[start:stop], chunk, k, cutoff)
    return inputs.output(torch.where(inputs.pixels >= 0, result, unprojected))


@torch.no_grad()
def pixel_classes(
    proj_argmax: Images,
    proj_x: Points,
    proj_y: Points,
    num_classes: int,
    *,
    unprojected: int = 0,
) -> ArrayLike:
    """Each point's pixel class, for B scans at once (no refinement), concatenated scan by scan.

    Inputs, checks and result as in `refine_batch`; points without a pixel get `unprojected`.
    """
    inputs = _Inputs(proj_argmax, proj_x, proj_y, num_classes)
    looked_up = inputs.classes.reshape(-1).index_select(0, inputs.pixels.clamp(min=0))
    return inputs.output(torch.where(inputs.pixels >= 0, looked_up, unprojected))


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


class _Inputs:
    """A batch's inputs checked and moved to one device.

    `image` and `classes` are (B, H, W) float32 and int64; `ranges` (N,) float32; `pixels` (N,)
    the flat index of each point's pixel in B * H * W, -1 for points without one. Numpy inputs are
    checked on the host before the copy; tensors on their device, where out-of-range values are
    clamped (never used as indices) and the checks wait for `output`, which reads them in one go.
    """

    def __init__(
        self,
        proj_argmax: Images,
        proj_x: Points,
        proj_y: Points,
        num_classes: int,
        proj_range: Images | None = None,
        unproj_range: Points | None = None,
    ) -> None:
        classes = _image_parts(proj_argmax, "proj_argmax")
        cols, rows = _point_parts(proj_x, "proj_x"), _point_parts(proj_y, "proj_y")
        images = None if proj_range is None else _image_parts(proj_range, "proj_range")
        ranges = None if unproj_range is None else _point_parts(unproj_range, "unproj_range")
        _check_shapes(images, classes, ranges, cols, rows)
        for name, parts, integer in (
            ("proj_argmax", classes, True),
            ("proj_x", cols, True),
            ("proj_y", rows, True),
            ("proj_range", images or [], False),
            ("unproj_range", ranges or [], False),
        ):
            _check_kind(parts, name, integer=integer)
        self.as_numpy, self.device = _output_kind(
            *classes, *cols, *rows, *(images or []), *(ranges or [])
        )
        self.deferred: list[tuple[Callable[[list[int]], str | None], torch.Tensor]] = []
        pinned = self.device.type == "cuda"
        _, height, width = classes[0].shape
        self.sizes = [part.shape[0] for part in cols]
        class_problem = functools.partial(_class_problem, num_classes=num_classes)
        point_problem = functools.partial(_point_problem, height=height, width=width)

        if _on_host(classes):
            for part in classes:
                if part.size:
                    _raise(class_problem([int(part.min()), int(part.max())]))
        self.classes = _moved(classes, torch.int64, self.device, pinned)
        if not _on_host(classes):
            if self.classes.numel():
                stats = torch.stack([self.classes.amin(), self.classes.amax()])
                self.deferred.append((class_problem, stats))
            self.classes = self.classes.clamp(0, num_classes - 1)

        if _on_host(cols) and _on_host(rows):
            pixels = []
            for scan, (x, y) in enumerate(zip(cols, rows, strict=True)):
                x, y = x.astype(np.int64, copy=False), y.astype(np.int64, copy=False)
                projected = x >= 0
                if x.size:
                    _raise(point_problem(_point_stats(x, y, projected, np.where)))
                offset = scan * height * width
                pixels.append(np.where(projected, offset + y * width + x, -1))
            self.pixels = to_device(pixels, torch.int64, self.device, pinned=pinned)
        else:
            x = [_moved([part], torch.int64, self.device, pinned) for part in cols]
            y = [_moved([part], torch.int64, self.device, pinned) for part in rows]
            self.pixels = torch.cat(
                [
                    torch.where(
                        xs >= 0,
                        scan * height * width
                        + ys.clamp(0, height - 1) * width
                        + xs.clamp(0, width - 1),
                        -1,
                    )
                    for scan, (xs, ys) in enumerate(zip(x, y, strict=True))
                ]
            )
            all_x, all_y = torch.cat(x), torch.cat(y)
            if all_x.numel():
                stats = torch.stack(_point_stats(all_x, all_y, all_x >= 0, torch.where))
                self.deferred.append((point_problem, stats))

        if images is not None:
            self.image = _moved(images, torch.float32, self.device, pinned)
        if ranges is not None:
            self.ranges = _moved(ranges, torch.float32, self.device, pinned)

    def output(self, result: torch.Tensor) -> ArrayLike:
        """`result` as the caller gets it, once the deferred checks of tensor inputs have passed."""
        if self.deferred:
            values = torch.cat([stats for _, stats in self.deferred]).tolist()
            for problem, stats in self.deferred:
                _raise(problem(values[: len(stats)]))
                values = values[len(stats) :]
        return result.cpu().numpy() if self.as_numpy else result


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


def _image_parts(value: Images, name: str) -> list[ArrayLike]:
    """An image input as (b, H, W) parts: a (B, H, W) array as it is, each (H, W) array as (1, H, W)."""
    if isinstance(value, np.ndarray | torch.Tensor):
        if value.ndim != 3:
            raise ValueError(
                f"{name} must be (B, H, W) or a list of (H, W) images, got shape {tuple(value.shape)}"
            )
        return [value]
    parts = [_array(part) for part in value]
    for part in parts:
        if part.ndim != 2:
            raise ValueError(f"{name} must be (H, W), got shape {tuple(part.shape)}")
    return [part[None] for part in parts]


def _point_parts(value: Points, name: str) -> list[ArrayLike]:
    """A point input as its (N_b,) arrays, one per scan."""
    if isinstance(value, np.ndarray | torch.Tensor):
        raise ValueError(f"{name} must be a list of (N,) arrays, one per scan")
    parts = [_array(part) for part in value]
    for part in parts:
        if part.ndim != 1:
            raise ValueError(f"{name} must be (N,), got shape {tuple(part.shape)}")
    return parts


def _array(value: object) -> ArrayLike:
    """A tensor as it is, anything else as a numpy array."""
    return value if isinstance(value, torch.Tensor) else np.asarray(value)


def _check_shapes(
    images: list[ArrayLike] | None,
    classes: list[ArrayLike],
    ranges: list[ArrayLike] | None,
    cols: list[ArrayLike],
    rows: list[ArrayLike],
) -> None:
    """Raise ValueError, naming the argument, for shapes that do not fit together."""
    scans = sum(part.shape[0] for part in classes)
    if scans == 0:
        raise ValueError("proj_argmax holds no image: a batch needs at least one scan")
    height, width = classes[0].shape[1:]
    if any(part.shape[1:] != (height, width) for part in classes):
        raise ValueError("proj_argmax must hold images of one size")
    if images is not None:
        shapes = [tuple(part.shape) for part in images]
        if sum(s[0] for s in shapes) != scans or any(s[1:] != (height, width) for s in shapes):
            raise ValueError(
                f"proj_argmax must have the shape of proj_range, got {scans} images of "
                f"{height} x {width} and proj_range of shapes {shapes}"
            )
    named = {"unproj_range": ranges, "proj_x": cols, "proj_y": rows}
    named = {name: parts for name, parts in named.items() if parts is not None}
    for name, parts in named.items():
        if len(parts) != scans:
            raise ValueError(f"{name} must hold one array per scan ({scans}), got {len(parts)}")
    for scan in range(scans):
        shapes = [tuple(parts[scan].shape) for parts in named.values()]
        if len(set(shapes)) > 1:
            raise ValueError(
                f"{', '.join(named)} must have the same shape (N,) in each scan, got "
                f"{', '.join(map(str, shapes))} in scan {scan}"
            )


def _check_kind(parts: list[ArrayLike], name: str, *, integer: bool) -> None:
    """Raise ValueError, naming the argument, for dtypes that are not real (integer) numbers."""
    for part in parts:
        if isinstance(part, torch.Tensor):
            kind = "f" if part.is_floating_point() else "b" if part.dtype == torch.bool else "i"
            kind = "c" if part.is_complex() else kind
        else:
            kind = part.dtype.kind
        if kind not in "fiu":
            raise ValueError(f"{name} must hold real numbers, got dtype {part.dtype}")
        if kind == "f" and integer:
            raise ValueError(f"{name} must hold integers, got dtype {part.dtype}")


def _on_host(parts: list[ArrayLike]) -> bool:
    """Whether every part is a numpy array."""
    return all(isinstance(part, np.ndarray) for part in parts)


def _moved(
    parts: list[ArrayLike], dtype: torch.dtype, device: torch.device, pinned: bool
) -> torch.Tensor:
    """The parts concatenated on `device`: numpy arrays through `to_device`, tensors there."""
    if _on_host(parts):
        return to_device(parts, dtype, device, pinned=pinned)
    tensors = [
        part.to(device=device, dtype=dtype)
        if isinstance(part, torch.Tensor)
        else to_device([part], dtype, device, pinned=pinned)
        for part in parts
    ]
    return tensors[0] if len(tensors) == 1 else torch.cat(tensors)


def _point_stats(x: ArrayLike, y: ArrayLike, projected: ArrayLike, where: Callable) -> list:
    """[min and max of x, min and max of y where x >= 0] as numpy or 0-d tensor values."""
    low, high = np.iinfo(np.int64).max, np.iinfo(np.int64).min
    return [x.min(), x.max(), where(projected, y, low).min(), where(projected, y, high).max()]


def _class_problem(stats: list[int], num_classes: int) -> str | None:
    """What is wrong with proj_argmax, given its [min, max]."""
    low, high = (int(v) for v in stats)
    if low < 0 or high >= num_classes:
        return f"proj_argmax must hold classes in [0, {num_classes}), got values in [{low}, {high}]"
    return None


def _point_problem(stats: list[int], height: int, width: int) -> str | None:
    """What is wrong with proj_x or proj_y, given `_point_stats`."""
    col_low, col_high, row_low, row_high = (int(v) for v in stats)
    if col_low < -1:
        return "proj_x must be -1 (not projected) or a column in [0, W)"
    if col_high >= width:
        return f"proj_x must be below the image width {width}, got {col_high}"
    if row_low <= row_high and (row_low < 0 or row_high >= height):
        return (
            f"proj_y must be in [0, {height}) for projected points, "
            f"got values in [{row_low}, {row_high}]"
        )
    return None


def _raise(problem: str | None) -> None:
    """Raise ValueError with `problem` when there is one."""
    if problem is not None:
        raise ValueError(problem)
