"""kNN refinement on the CPU (`rangeret.inference.knn`): the fast path over int16 keys, and the
exact rule (`rangeret.inference.knn_rule`) for the points it leaves open.

Each distance, exactly as the published code rounds it, times a float32 scale, truncated, is a
bucket: a non-decreasing function of the distance, so two distances in different buckets are in
the exact order, a bucket below the cutoff's (`unsure`) is within the cutoff and one above it
beyond. A bucket and the class code make an int16 key, and one int16 network over the keys finds
the k - 1 voters and their classes at once. A point is settled unless its (k-1)-th and k-th keys
share a bucket below `unsure` or a voter's bucket is `unsure`; those go through the exact rule.
Here the host is the device, so the layout may depend on the data: up to two layers of at most
one point per pixel (the last and the first point of each pixel), where they fill much of the
image they span, are computed densely over the padded image (each neighbour's row a shifted
slice of it), and the remaining points gather their windows by index. The keys' filler is the
smallest key beyond the cutoff, with the code of a voter that abstains, so the network hands the
vote its voters' codes as they are. Temporaries live in buffers kept per thread (`_Workspace`,
`_scratch`): fresh ones would cost a page fault per 4 kB touched.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from functools import partial

import numpy as np
import torch

from rangeret.inference.knn_rule import (
    Window,
    gaussian_kernel,
    majority,
    padding_code,
    small_int_dtype,
    smallest,
)
from rangeret.inference.settings import KnnSettings

__all__ = ["refine_on_cpu"]

#: What writes the keys of a range of columns (see `_Quantized._columns`).
_KeysOf = Callable[[int, int, torch.Tensor, "_Workspace"], None]
#: What gives the centre codes of a range of columns (see `_Quantized._columns`).
_CentresOf = Callable[[int, int, "_Workspace"], torch.Tensor]
#: A layer of a scan's points is computed densely when its points times this cost ratio (a point
#: gathered by index against a pixel computed in place) reach the pixels it spans.
_GATHER_COST = 2.0


def refine_on_cpu(
    result: np.ndarray,
    classes: np.ndarray,
    image: np.ndarray,
    ranges: np.ndarray,
    proj_x: np.ndarray,
    proj_y: np.ndarray,
    knn: KnnSettings,
    num_classes: int,
    votes_from: int,
    chunk_size: int,
    piece: int,
) -> None:
    """Write the classes of one scan's points that have a pixel into `result`, on the CPU,
    at most `chunk_size` points (or columns) at once, their distances `piece` at a time.

    The fast path where it applies, the exact rule for the points it leaves open; the exact
    rule for all when the cutoff is off, the class codes too wide or a range not a number.
    """
    everywhere = bool(proj_x.min() >= 0)  # the common case: no index list to make
    valid = np.arange(0) if everywhere else np.flatnonzero(proj_x >= 0)
    if not (everywhere or valid.size):
        return
    padded = _Padded(image, classes, knn.search, num_classes, votes_from)
    columns = padded.columns(proj_x, proj_y)
    weights = (1.0 - gaussian_kernel(knn.search, knn.sigma)).numpy().reshape(-1)
    neighbours = torch.from_numpy(np.delete(weights, padded.centre))[:, None]

    def exact(points: np.ndarray) -> None:
        for start in range(0, points.size, chunk_size):
            chunk = points[start : start + chunk_size]
            window = padded.window(np.take(columns, chunk), neighbours, num_classes, votes_from)
            near = torch.from_numpy(np.take(ranges, chunk))
            result[chunk] = window.vote(near, None, knn.k, knn.cutoff).numpy()

    projected = ranges if everywhere else np.take(ranges, valid)
    if not _Quantized.applies(image, projected, knn, num_classes, weights):
        exact(np.arange(ranges.size) if everywhere else valid)
    elif everywhere:
        fast = _Quantized(padded, knn, num_classes, votes_from, weights)
        exact(fast.refine(ranges, columns, result, chunk_size, piece))
    else:
        fast = _Quantized(padded, knn, num_classes, votes_from, weights)
        spots = np.take(columns, valid)
        found = np.empty(valid.size, dtype=np.int64)
        left_open = fast.refine(projected, spots, found, chunk_size, piece)
        result[valid] = found
        exact(np.take(valid, left_open))


class _Padded:
    """One scan's range image and class codes, padded by S // 2 on every side and flattened.

    A position in it is a "column": neighbour j of column c is column c + offsets[j]. `far` holds
    the ranges (empty pixels at +inf, the padding at 0), `codes` the class codes (see
    `majority`; the padding holds class 0's).
    """

    def __init__(
        self,
        image: np.ndarray,
        classes: np.ndarray,
        search: int,
        num_classes: int,
        votes_from: int,
    ) -> None:
        height, width = image.shape
        pad = search // 2
        self.search = search
        self.pad = pad
        self.stride = width + 2 * pad
        self.cells = search * search
        self.centre = self.cells // 2
        shape = (height + 2 * pad, self.stride)
        far = _scratch("far", shape[0] * shape[1], np.float32).reshape(shape)
        far.fill(0)
        inside = far[pad : pad + height, pad : pad + width]
        np.copyto(inside, image)
        inside[image < 0] = np.inf
        self.far = torch.from_numpy(far.reshape(-1))
        codes = _scratch("codes", far.size, np.int16).reshape(shape)
        codes.fill(padding_code(num_classes, votes_from))
        inside = codes[pad : pad + height, pad : pad + width]
        np.subtract(num_classes + 1, classes, out=inside, casting="unsafe")
        inside[classes < votes_from] = 0
        self.codes = torch.from_numpy(codes.reshape(-1))
        rows, cols = np.divmod(np.arange(self.cells), search)
        self.offsets = torch.from_numpy(((rows - pad) * self.stride + cols - pad).astype(np.int32))

    def columns(self, proj_x: np.ndarray, proj_y: np.ndarray) -> np.ndarray:
        """(N,) int64 columns of the points' pixels (meaningless for points without one), in
        this thread's buffer."""
        columns = _scratch("columns", proj_x.size, np.int64)
        np.multiply(proj_y, self.stride, out=columns, dtype=np.int64)
        columns += proj_x
        columns += self.pad * self.stride + self.pad
        return columns

    def window(
        self, columns: np.ndarray, weights: torch.Tensor, num_classes: int, votes_from: int
    ) -> Window:
        """The exact rule's window gathered for points at `columns`, one window column each."""
        around = self.offsets[:, None] + torch.from_numpy(columns)
        keep = torch.from_numpy(np.delete(np.arange(self.cells), self.centre))
        around = around.index_select(0, keep).view(-1)
        shape = (self.cells - 1, len(columns))
        code_dtype = small_int_dtype(num_classes + 1)
        return Window(
            self.far.index_select(0, around).view(shape),
            self.codes.index_select(0, around).view(shape).to(code_dtype),
            self.codes.index_select(0, torch.from_numpy(columns)).to(code_dtype),
            weights,
            num_classes,
            votes_from,
        )


class _Quantized:
    """The CPU's fast path over one scan: int16 keys from scaled distances (see the module)."""

    def __init__(
        self,
        padded: _Padded,
        knn: KnnSettings,
        num_classes: int,
        votes_from: int,
        weights: np.ndarray,
    ) -> None:
        self.padded = padded
        self.search = padded.search
        self.cells = padded.cells
        self.centre = padded.centre
        self.num_classes = num_classes
        self.votes_from = votes_from
        self.bits, unsure, self.scale = _quantization(num_classes, knn.cutoff)
        self.limit = unsure + 1
        # Buckets 0..2^(16 - bits) - 1 are stored less `offset`, so that the keys use the whole
        # int16 range; `unsure` is the cutoff's bucket as stored.
        self.offset = 1 << (15 - self.bits)
        self.unsure = unsure - self.offset
        # the network's filler: the smallest key beyond the cutoff, code 0 (abstains)
        self.fill = (self.limit - self.offset) << self.bits
        # added to a key, maps the keys of the `unsure` bucket to the lowest int16 values
        self.wrap = (-(self.unsure << self.bits)) % (1 << 16) - (1 << 15)
        self.weights = torch.from_numpy(weights).reshape(self.search, self.search, 1)
        # the class codes less offset << bits = 2^15, a multiple of 256: as uint8 they are the
        # codes again
        shifted = _scratch("shifted codes", len(padded.codes), np.int16)
        self.codes = torch.add(padded.codes, -(1 << 15), out=torch.from_numpy(shifted))
        self.wanted = knn.k - 1
        self.ranked = min(self.wanted + 1, self.cells - 1)  # the network's length

    @staticmethod
    def applies(
        image: np.ndarray,
        ranges: np.ndarray,
        knn: KnnSettings,
        num_classes: int,
        weights: np.ndarray,
    ) -> bool:
        """Whether the fast path applies: a finite positive cutoff (as float32) that a finite
        scale puts in a bucket, class codes that leave at least 7 bits of distance, point
        ranges finite and no NaN in the image (NaN distances have no order)."""
        if (num_classes + 1).bit_length() > 8 or _quantization(num_classes, knn.cutoff)[1] < 1:
            return False
        # min and max are NaN where any value is, and infinite where one is
        return bool(
            np.isfinite(ranges.min()) and np.isfinite(ranges.max()) and not np.isnan(image.max())
        )

    def refine(
        self,
        ranges: np.ndarray,
        spots: np.ndarray,
        result: np.ndarray,
        chunk_size: int,
        piece: int,
    ) -> np.ndarray:
        """Write the classes of the points with `ranges` at columns `spots` into `result`, -1
        for those left open; return their indices.

        Two layers are computed densely over the columns the points span while they fill
        enough of them: a range image of the points written in order, then in reverse (each
        pixel's last point, then its first); a point whose range is its pixel's is in the layer,
        its keys being the pixel's, so the order numpy writes in never changes a label. The
        points left over are gathered by index. Masks rather than index lists, host arrays in
        this thread's buffers: fresh ones cost a page fault per 4 kB.
        """
        n = spots.size
        low = int(spots.min())
        top = int(spots.max()) + 1
        span = top - low
        # images and classes by column (those below `low` unused), masks by point
        image = _scratch("image", top, np.float32)
        classes = _scratch("layer classes", top, np.int64)
        members = [_scratch("last", n, np.bool_), _scratch("first", n, np.bool_)]
        dense = 0
        for order, member in zip((slice(None), slice(None, None, -1)), members, strict=True):
            image[low:].fill(0)
            image[spots[order]] = ranges[order]
            np.equal(np.take(image, spots, out=_scratch("near", n, np.float32)), ranges, out=member)
            if dense:
                np.greater(member, members[0], out=member)  # new to this layer
            if np.count_nonzero(member) * _GATHER_COST < span:
                break
            dense += 1
            keys_of = partial(self._dense_keys, torch.from_numpy(image[low:]), low)
            centres_of = partial(self._dense_centres, low)
            self._columns(keys_of, centres_of, span, chunk_size, piece, classes[low:])
            layer = np.take(classes, spots, out=_scratch("classes", n, np.int64))
            np.copyto(result, layer, where=member)
        if dense == 2:
            np.logical_or(members[0], members[1], out=members[0])
        done = members[0] if dense else np.zeros(n, dtype=np.bool_)
        rest = np.flatnonzero(~done)
        if rest.size:
            near = torch.from_numpy(np.take(ranges, rest))
            columns = torch.from_numpy(np.take(spots, rest).astype(np.int32))
            keys_of = partial(self._gathered_keys, columns, near)
            centres_of = partial(self._gathered_centres, columns)
            found = _scratch("found", rest.size, np.int64)
            result[rest] = self._columns(keys_of, centres_of, rest.size, chunk_size, piece, found)
        return np.flatnonzero(result < 0)

    def _columns(
        self,
        keys_of: _KeysOf,
        centres_of: _CentresOf,
        count: int,
        chunk_size: int,
        piece: int,
        out: np.ndarray,
    ) -> np.ndarray:
        """Classes (int64, -1 where open) of the `count` columns of one source into `out`, in
        even chunks of at most `chunk_size`.

        keys_of(start, stop, out, work) writes the (S, S, stop - start) keys of the source's
        columns start..stop into `out`, its temporaries in `work`, and centres_of(start, stop,
        work) gives their centre codes; pieces of at most `piece` columns keep the float32
        distances in cache.
        """
        chunk = -(-count // -(-count // chunk_size))
        work = _Workspace.of_thread(self.cells, self.ranked, chunk)
        classes = torch.from_numpy(out)
        settled = work.take("all settled", (count,), torch.int16)
        for start in range(0, count, chunk):
            stop = min(start + chunk, count)
            for begin in range(start, stop, piece):
                end = min(begin + piece, stop)
                shape = (self.search, self.search, end - begin)
                out = work.keys[:, begin - start : end - start].view(shape)
                keys_of(begin, end, out, work)
            best = smallest(
                work.keys[:, : stop - start],
                self.ranked,
                self.fill,
                skip=self.centre,
                out=work.network(stop - start),
            )
            centres = centres_of(start, stop, work)
            settled[start:stop] = self._decide(best, centres, work, classes[start:stop])
        return classes.masked_fill_(settled == 0, -1).numpy()

    def _dense_keys(
        self,
        image: torch.Tensor,
        first: int,
        start: int,
        stop: int,
        out: torch.Tensor,
        work: _Workspace,
    ) -> None:
        """Keys of columns first + start..stop of a layer, whose ranges `image` holds from
        column `first`: each neighbour's ranges are a shifted slice of `far`."""
        padded = self.padded
        floats = work.take("floats", out.shape, torch.float32)
        origin = first + start - padded.pad * padded.stride - padded.pad
        strides = (padded.stride, 1, 1)
        window = padded.far.as_strided(floats.shape, strides, origin)
        torch.sub(window, image[start:stop], out=floats)
        self._keys(floats, self.codes.as_strided(floats.shape, strides, origin), out)

    def _dense_centres(self, first: int, start: int, stop: int, work: _Workspace) -> torch.Tensor:
        """Centre codes of columns first + start..stop of a layer (a slice, no copy)."""
        return self.codes[first + start : first + stop]

    def _gathered_centres(
        self, columns: torch.Tensor, start: int, stop: int, work: _Workspace
    ) -> torch.Tensor:
        """Centre codes of points start..stop of those at `columns` (int32)."""
        return torch.index_select(
            self.codes, 0, columns[start:stop], out=work.centres[: stop - start]
        )

    def _gathered_keys(
        self,
        columns: torch.Tensor,
        ranges: torch.Tensor,
        start: int,
        stop: int,
        out: torch.Tensor,
        work: _Workspace,
    ) -> None:
        """Keys of points start..stop of those at `columns` (int32) with their `ranges`, their
        windows gathered by index."""
        padded = self.padded
        shape = (self.cells, stop - start)
        around = work.take("around", shape, torch.int32)
        around = torch.add(padded.offsets[:, None], columns[start:stop], out=around).view(-1)
        floats = work.take("floats", out.shape, torch.float32)
        torch.index_select(padded.far, 0, around, out=floats.view(-1))
        floats.sub_(ranges[start:stop])
        codes = work.take("codes", shape, torch.int16).view(floats.shape)
        torch.index_select(self.codes, 0, around, out=codes.view(-1))
        self._keys(floats, codes, out)

    def _keys(self, diff: torch.Tensor, codes: torch.Tensor, out: torch.Tensor) -> None:
        """out = code + ((bucket - offset) << bits), bucket = trunc(min(|diff| * weight * scale,
        limit)), from `codes` less offset << bits = 2^15 (see `_Quantized`): the product may wrap
        in int16, the sum does not.

        |diff| * weight is the published distance, rounded as it is; the sign is dropped after
        rounding, as (-x) * w rounds to -(x * w) and truncation is symmetric too.
        """
        diff.mul_(self.weights).mul_(self.scale).clamp_(-self.limit, self.limit)
        out.copy_(diff)
        torch.add(codes, out.abs_(), alpha=1 << self.bits, out=out)

    def _decide(
        self,
        best: torch.Tensor,
        centre: torch.Tensor,
        work: _Workspace,
        out: torch.Tensor,
    ) -> torch.Tensor:
        """Classes of columns (in `out`) from the network's smallest keys and their centre codes
        (as uint8: see `_Quantized`), and an int16 per column that is 0 where the column is open
        (returned); temporaries in `work`'s buffers.

        Keys beyond the cutoff came out of the network as the filler, whose code is 0 (abstains),
        so a voter's code is its key's low bits. Written in integer arithmetic (shifts, minima):
        comparisons of int16 rows into bool rows take several times longer on the CPU.
        """
        wanted, n = self.wanted, len(centre)
        take = work.take
        votes = take("votes", (wanted + 1, n), torch.uint8)
        votes[0] = centre
        if wanted == 0:
            majority(votes, self.num_classes, self.votes_from, take, out)
            return take("settled", (n,), torch.int16).fill_(1)
        chosen = best[:wanted]
        # 0 where a voter's key is in the `unsure` bucket: those keys wrap to the lowest ones,
        wrapped = torch.add(chosen, self.wrap, out=take("wrapped", (wanted, n), torch.int16))
        settled = torch.amin(wrapped, 0, out=take("settled", (n,), torch.int16))
        settled.bitwise_right_shift_(self.bits).add_(1 << (15 - self.bits))
        if wanted < len(best):
            # or where the k-th key shares the (k-1)-th's bucket, when that is below `unsure`
            kth = torch.bitwise_right_shift(
                chosen[-1], self.bits, out=take("kth", (n,), torch.int16)
            )
            apart = torch.bitwise_right_shift(
                best[wanted], self.bits, out=take("apart", (n,), torch.int16)
            ).sub_(kth)
            apart += kth.sub_(self.unsure - 1).clamp_(0, 1)
            torch.minimum(settled, apart, out=settled)
        torch.bitwise_and(chosen, (1 << self.bits) - 1, out=votes[1:])
        majority(votes, self.num_classes, self.votes_from, take, out)
        return settled


class _Workspace:
    """Buffers every chunk reuses, one set per thread kept between calls (fresh ones would cost
    page faults each time)."""

    _cache = threading.local()

    def __init__(self, cells: int, ranked: int, chunk: int) -> None:
        self.shape = (cells, ranked, chunk)
        self.keys = torch.empty(cells, chunk, dtype=torch.int16)
        self.centres = torch.empty(chunk, dtype=torch.int16)
        self.lists = torch.empty(2, ranked + 1, chunk, dtype=torch.int16)
        self.buffers: dict[str, torch.Tensor] = {}

    @classmethod
    def of_thread(cls, cells: int, ranked: int, chunk: int) -> _Workspace:
        """This thread's buffers for the current inference mode (a tensor made under
        `torch.inference_mode` may not be written outside it), made anew when they do not fit."""
        works: dict[bool, _Workspace] = cls._cache.__dict__.setdefault("works", {})
        mode = torch.is_inference_mode_enabled()
        work = works.get(mode)
        if work is None or work.shape[:2] != (cells, ranked) or work.shape[2] < chunk:
            work = works[mode] = cls(cells, ranked, chunk)
        return work

    def take(self, name: str, shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
        """The buffer `name` as a tensor of `shape` and `dtype` (contents undefined)."""
        size = math.prod(shape)
        buffer = self.buffers.get(name)
        if buffer is None or buffer.dtype != dtype or buffer.numel() < size:
            buffer = self.buffers[name] = torch.empty(size, dtype=dtype)
        return buffer[:size].view(shape)

    def network(self, columns: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The insertion network's two buffers for `columns` columns."""
        return self.lists[0, :, :columns], self.lists[1, :, :columns]


_HOST = threading.local()


def _scratch(name: str, size: int, dtype: type) -> np.ndarray:
    """This thread's host buffer `name` as `size` items of `dtype` (contents undefined), kept
    between calls: a fresh array costs a page fault per 4 kB touched."""
    pool: dict[str, np.ndarray] = _HOST.__dict__.setdefault("pool", {})
    buffer = pool.get(name)
    if buffer is None or buffer.dtype != dtype or buffer.size < size:
        buffer = pool[name] = np.empty(size, dtype=dtype)
    return buffer[:size]


def _quantization(num_classes: int, cutoff: float) -> tuple[int, int, float]:
    """Bits of a class code, the bucket of the cutoff (`unsure`) and the distance scale.

    A key is an int16: the class code in its low `bits`, the bucket trunc(distance * scale),
    float32 rounded like the distance, above them (less half its range, see `_Quantized`). The
    bucket is a non-decreasing function of the distance, the cutoff's bucket `unsure` holds
    distances on both sides of the cutoff, and `unsure` + 1, the largest bucket, everything
    beyond it. A cutoff that is not a finite positive float32 gives an `unsure` of -1.
    """
    bits = (num_classes + 1).bit_length()
    largest = (1 << (16 - bits)) - 1
    with np.errstate(over="ignore"):
        limit = np.float32(cutoff)
        if not (np.isfinite(limit) and limit > 0):
            return bits, -1, 0.0
        scale = np.float32((largest - 0.5) / np.float64(limit))
        scaled = limit * scale
    unsure = int(scaled) if np.isfinite(scaled) and scaled < largest else -1
    return bits, unsure, float(scale)
