"""The exact rule of kNN refinement in torch (`rangeret.inference.knn`) and the pieces the
compiled vote shares with it: the window weights, the padding's class code, host arrays to the
device.

`Window` holds the S x S neighbourhood of a set of columns (pixels of range images, or points
whose windows were gathered) and applies the rule, ties included, to chunks of points: the
neighbours below the (k-1)-th distance, then those at it, are compacted into k - 1 slots by a
second network over small integer keys, and their classes are counted. It makes no
data-dependent shapes, so on a device the host never waits for it.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache

import numpy as np
import torch
import torch.nn.functional as F

__all__ = [
    "Window",
    "gaussian_kernel",
    "majority",
    "padding_code",
    "small_int_dtype",
    "smallest",
    "to_device",
]

#: Most voters whose counts `majority` takes from all pairs at once.
_BROADCAST_VOTERS = 16


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


def padding_code(num_classes: int, votes_from: int) -> int:
    """The code of the zero padding: class 0's (C + 1 where it votes, 0 where it abstains)."""
    return num_classes + 1 if votes_from == 0 else 0


class Window:
    """The S x S neighbourhood of P columns (pixels of B range images, or gathered points), ready
    to be gathered per point.

    `ranges` is a (S^2 - 1, P) table of neighbour ranges (centre left out, empty pixels at +inf,
    zero padding outside each image); `codes` the matching neighbour class codes (see
    `majority`), flattened, as rows that the compaction keys of `_keys` index directly.
    """

    def __init__(
        self,
        ranges: torch.Tensor,
        codes: torch.Tensor,
        centre_codes: torch.Tensor,
        weights: torch.Tensor,
        num_classes: int,
        votes_from: int,
    ) -> None:
        self.size, self.pixels = ranges.shape
        device = ranges.device
        self.ranges = ranges
        self.weights = weights
        self.centre_codes = centre_codes
        self.num_classes = num_classes
        self.votes_from = votes_from

        # Compaction keys: j for neighbour j below the threshold, size + j at it, 2 size + j
        # beyond it. Rows of `codes` follow the keys, all keys from `empty` = 2 size on reading
        # its row of zeros; a code is C + 1 - class for a class that votes, 0 for one that does
        # not and for `empty`; the padding holds class 0's code (see `majority`).
        self.empty = 2 * self.size
        self.key_dtype = small_int_dtype(3 * self.size)
        self.positions = torch.arange(self.size, device=device, dtype=self.key_dtype)[:, None]
        self.codes = torch.cat([codes, codes, codes.new_zeros(1, self.pixels)]).reshape(-1)
        fits = self.codes.numel() < torch.iinfo(torch.int32).max
        self.index_dtype = torch.int32 if fits else torch.int64

    @classmethod
    def of_images(
        cls,
        image: torch.Tensor,
        classes: torch.Tensor,
        search: int,
        sigma: float,
        num_classes: int,
        votes_from: int,
    ) -> Window:
        """The window over every pixel of (B, H, W) range `image` and `classes`."""
        _, height, width = image.shape
        pad = search // 2
        device = image.device
        offsets = [
            (dy, dx) for dy in range(search) for dx in range(search) if (dy, dx) != (pad, pad)
        ]
        weights = (1.0 - gaussian_kernel(search, sigma)).reshape(-1)
        centre = search * search // 2
        weights = torch.cat([weights[:centre], weights[centre + 1 :]])
        weights = to_device([weights.numpy()], torch.float32, device, pinned=device.type == "cuda")

        far = torch.where(image < 0, torch.full_like(image, float("inf")), image)
        far = F.pad(far, (pad, pad, pad, pad))
        code_dtype = small_int_dtype(num_classes + 1)
        inverted = torch.where(classes >= votes_from, num_classes + 1 - classes, 0).to(code_dtype)
        padding = padding_code(num_classes, votes_from)
        neighbours = _shifted(
            F.pad(inverted, (pad, pad, pad, pad), value=padding), offsets, height, width
        )
        return cls(
            _shifted(far, offsets, height, width),
            neighbours,
            inverted.reshape(-1),
            weights[:, None],
            num_classes,
            votes_from,
        )

    def vote(
        self, ranges: torch.Tensor, pixels: torch.Tensor | None, k: int, cutoff: float
    ) -> torch.Tensor:
        """Classes of one chunk of points, given by their range and column (flat pixel index);
        `pixels` None for a window gathered for these points, one column each in order (its
        range table is used up)."""
        if pixels is None:
            centre = self.centre_codes
            pixels = torch.arange(self.pixels, device=ranges.device)
            dist = self.ranges
        else:
            centre = self.centre_codes.index_select(0, pixels)
            dist = self.ranges.index_select(1, pixels)
        voters = [centre[None]]
        wanted = k - 1  # neighbours besides the centre, whose distance is 0
        if wanted and self.size:
            dist.sub_(ranges).abs_().mul_(self.weights)
            keys = self._keys(dist, wanted, cutoff)
            slots = keys if wanted >= self.size else smallest(keys, wanted, self.empty)
            slots = slots.clamp(max=self.empty)
            index = slots.to(self.index_dtype).mul_(self.pixels).add_(pixels.to(self.index_dtype))
            voters.append(self.codes.index_select(0, index.reshape(-1)).reshape(slots.shape))
        return majority(torch.cat(voters), self.num_classes, self.votes_from)

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
        kth = smallest(dist, wanted, float("inf"))[wanted - 1]
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


def small_int_dtype(largest: int) -> torch.dtype:
    """The narrowest of uint8, int16 and int32 that holds 0..largest (narrow rows run faster)."""
    if largest <= torch.iinfo(torch.uint8).max:
        return torch.uint8
    if largest <= torch.iinfo(torch.int16).max:
        return torch.int16
    return torch.int32


def smallest(values: torch.Tensor, count: int, fill: float | int) -> torch.Tensor:
    """The `count` smallest of each column of (m, n) `values`, ascending, as (count, n).

    An insertion network: `current` holds the smallest so far behind a lower-bound guard row, and
    adding x makes row i min(row i, max(row i-1, x)) = clamp(x, row i-1, row i), all rows in one
    call; while fewer than `count` are in, the rows past them hold `fill` and stay so. Entries
    that do not exist (count > m) are `fill`.
    """
    n = values.shape[1]
    low = -float("inf") if values.dtype.is_floating_point else torch.iinfo(values.dtype).min
    current = torch.empty((count + 1, n), dtype=values.dtype, device=values.device)
    current[1:] = fill
    current[0] = low
    spare = current.clone()
    rows = values.unbind(0)
    # the two buffers take turns: views of both directions made once
    steps = [(current[:-1], current[1:], spare[1:]), (spare[:-1], spare[1:], current[1:])]
    for i, row in enumerate(rows):
        low_rows, high_rows, into = steps[i % 2]
        if i + 1 < count:  # rows i + 1.. hold `fill` in both buffers
            low_rows, high_rows, into = low_rows[: i + 1], high_rows[: i + 1], into[: i + 1]
        torch.clamp(row, min=low_rows, max=high_rows, out=into)
    return (spare if len(rows) % 2 else current)[1:]


def majority(codes: torch.Tensor, num_classes: int, votes_from: int) -> torch.Tensor:
    """Most frequent class of each column of (k, n) voter `codes` among classes votes_from..C-1.

    A code is C + 1 - class, and 0 for a voter that abstains. Ties go to the lowest class id (the
    highest code); a column without a vote gets class `votes_from`. Each voter scores
    count * (C + 2) + code (0 when it abstains): the largest score is the most votes, then the
    lowest class, and a lookup table turns it back into a class.
    """
    k, _ = codes.shape
    base = num_classes + 2
    top = k * base + num_classes + 1
    dtype = small_int_dtype(top)
    codes = codes.to(dtype)
    if k <= _BROADCAST_VOTERS:  # all k x k comparisons in one call, k^2 bytes a column
        same = torch.eq(codes[None], codes[:, None])
        counts = torch.sum(same.view(torch.uint8), 0, dtype=dtype)
    else:
        counts = torch.zeros_like(codes)
        same = torch.empty(codes.shape, dtype=torch.bool, device=codes.device)
        for row in codes:
            torch.eq(codes, row, out=same)
            counts += same
    # an abstaining voter (code 0) scores 0: multiplied by min(code, 1)
    scores = torch.add(codes, counts, alpha=base).mul_(codes.clamp(max=1))
    best = torch.amax(scores, 0)
    classes = _score_classes(top, num_classes, votes_from, codes.device)
    index_dtype = torch.int32 if top < 2**31 else torch.int64
    return torch.index_select(classes, 0, best.to(index_dtype))


@lru_cache(maxsize=64)
def _score_classes(
    top: int, num_classes: int, votes_from: int, device: torch.device
) -> torch.Tensor:
    """The class of each `majority` score 0..top, made once per rule and device (read only)."""
    table = torch.arange(top + 1, device=device)
    return torch.where(table == 0, votes_from, num_classes + 1 - table % (num_classes + 2))
