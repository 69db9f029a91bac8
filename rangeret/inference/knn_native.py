"""kNN refinement's compiled vote on the CPU: `csrc/knn_vote.c`, built with the package as the
shared library `_knn_vote` and called through ctypes.

The library holds the exact rule (`rangeret.inference.knn`) for one point per vector lane, in
AVX-512, AVX2 or baseline instructions, whichever the CPU runs best. A scan's points are split
into even ranges, one per torch intra-op thread, run side by side on threads of a pool (ctypes
lets go of the GIL during the call). The library is looked for beside this module, then in the
other copies of the package on the import path (a Ray job running from an uploaded copy of the
sources, which holds no compiled file, takes the installed one's), and taken only when its
functions are this module's version (`ABI`). Where there is none (a build without a C compiler)
or a scan is outside what it takes (a range that is not a number, more than `slots()` voters),
`vote_on_cpu` says so and the caller runs the exact rule in torch.
"""

from __future__ import annotations

import ctypes
import importlib.machinery
import logging
import os
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from functools import cache, lru_cache
from pathlib import Path

import numpy as np
import torch

from rangeret.inference.knn_rule import gaussian_kernel, padding_code
from rangeret.inference.settings import KnnSettings

__all__ = ["ABI", "ISA_NAMES", "best_isa", "built", "describe", "slots", "vote_on_cpu"]

log = logging.getLogger(__name__)

#: The version of the library's functions this module calls (`rangeret_knn_abi`): raised with
#: every change to their arguments, so that a library built from other sources is left out.
ABI = 1
#: The instruction sets the library is compiled for, by the number it calls them.
ISA_NAMES = {1: "baseline", 2: "AVX2", 3: "AVX-512"}
#: Points per lane group: ranges split between threads start at multiples of it.
_ALIGN = 16
_POINTER = ctypes.c_void_p
_I32 = ctypes.c_int32
_I64 = ctypes.c_int64


@cache
def _library() -> ctypes.CDLL | None:
    """The compiled library, looked for and loaded once; None where none was built."""
    return _load(tuple(_folders()))


def _folders() -> list[Path]:
    """Where the library may be, first found first: beside this module, then in every other
    copy of the package this interpreter could import (an installed one, where a Ray job runs
    from an uploaded copy of the sources, which holds no compiled file)."""
    here = Path(__file__).resolve().parent
    found = [here]
    places = [Path(entry) / "rangeret" for entry in sys.path if entry]
    for finder in sys.meta_path:
        find_spec = getattr(finder, "find_spec", None)
        try:
            spec = find_spec("rangeret", None) if find_spec else None
        except (ImportError, TypeError, ValueError):
            spec = None
        places += [Path(p) for p in (spec.submodule_search_locations or [])] if spec else []
    for place in places:
        folder = (place / "inference").resolve()
        if folder not in found and folder.is_dir():
            found.append(folder)
    return found


@cache
def _load(folders: tuple[Path, ...]) -> ctypes.CDLL | None:
    """The first library `_knn_vote` of this version (`ABI`) in `folders`, with its functions'
    types; None, logged once, where there is none."""
    for folder in folders:
        for suffix in importlib.machinery.EXTENSION_SUFFIXES:
            path = folder / f"_knn_vote{suffix}"
            library = _opened(path) if path.is_file() else None
            if library is not None:
                if folder != folders[0]:
                    log.info("kNN refinement's compiled vote comes from %s", path)
                return library
    log.warning(
        "kNN refinement's compiled vote (%s/_knn_vote*.so) is not built: the CPU runs the exact "
        "rule in torch, several times slower; reinstall the package where a C compiler is found",
        folders[0],
    )
    return None


def _opened(path: Path) -> ctypes.CDLL | None:
    """The library at `path` with its functions' types, or None where it is of another version
    or cannot be loaded (logged)."""
    try:
        library = ctypes.CDLL(str(path))
        version = library.rangeret_knn_abi
    except (OSError, AttributeError) as error:
        log.info("kNN refinement's compiled vote at %s is left out: %s", path, error)
        return None
    version.restype = _I32
    if version() != ABI:
        log.info("kNN refinement's compiled vote at %s is version %d, not %d", path, version(), ABI)
        return None
    library.rangeret_knn_vote.argtypes = [
        _I32,  # isa
        _POINTER,  # far
        _POINTER,  # codes
        _I32,  # height
        _I32,  # width
        _I32,  # pad
        _POINTER,  # offsets
        _POINTER,  # weights
        _I32,  # size
        _POINTER,  # ranges
        _POINTER,  # proj_x
        _POINTER,  # proj_y
        _I64,  # start
        _I64,  # stop
        _I32,  # wanted
        _I32,  # use_cutoff
        ctypes.c_float,  # cutoff
        _I32,  # num_classes
        _I32,  # votes_from
        _POINTER,  # out
    ]
    library.rangeret_knn_vote.restype = _I32
    library.rangeret_knn_slots.restype = _I32
    library.rangeret_knn_best_isa.restype = _I32
    return library


def built() -> bool:
    """Whether the compiled library is there."""
    return _library() is not None


def slots() -> int:
    """The most neighbours a point may keep (k - 1) in the library; 0 where it is not built."""
    library = _library()
    return 0 if library is None else int(library.rangeret_knn_slots())


def best_isa() -> int:
    """The best instruction set of `ISA_NAMES` this CPU runs the library in; 0 where it is not
    built."""
    library = _library()
    return 0 if library is None else int(library.rangeret_knn_best_isa())


def describe(device: str = "cpu") -> str:
    """Where and how kNN refinement votes on `device`, in one clause for people."""
    if device.split(":", 1)[0] != "cpu":
        return f"the exact rule in torch on {device}"
    isa = best_isa()
    if not isa:
        return "the exact rule in torch: the compiled vote is not built (no C compiler at install)"
    lanes = {1: 4, 2: 8, 3: 16}[isa]
    return f"the compiled vote, {ISA_NAMES[isa]} ({lanes} points a vector)"


class _Pool:
    """Threads that run parts of a scan beside the calling thread, grown on demand, and made
    anew in a forked child (which has none of its parent's threads)."""

    _lock = threading.Lock()
    _executor: ThreadPoolExecutor | None = None
    _size = 0

    @classmethod
    def get(cls, workers: int) -> ThreadPoolExecutor:
        """A pool of at least `workers` threads."""
        with cls._lock:
            if cls._executor is None or cls._size < workers:
                cls._executor = ThreadPoolExecutor(workers, thread_name_prefix="knn-vote")
                cls._size = workers
            return cls._executor

    @classmethod
    def forget(cls) -> None:
        """Drop the pool without waiting for it: in a forked child its threads do not exist."""
        cls._lock = threading.Lock()
        cls._executor = None
        cls._size = 0


os.register_at_fork(after_in_child=_Pool.forget)


@lru_cache(maxsize=16)
def _window(search: int, sigma: float, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """The neighbours of a search x search window, centre left out, in rows of `stride` values:
    their int32 offsets from the centre and float32 weights (1 - the Gaussian), made once per
    window and image width (read only)."""
    pad = search // 2
    rows, cols = np.divmod(np.arange(search * search), search)
    centre = search * search // 2
    offsets = np.delete((rows - pad) * stride + cols - pad, centre).astype(np.int32)
    weights = (1.0 - gaussian_kernel(search, sigma)).numpy().reshape(-1)
    weights = np.ascontiguousarray(np.delete(weights, centre))
    offsets.flags.writeable = weights.flags.writeable = False
    return offsets, weights


def vote_on_cpu(
    result: np.ndarray,
    classes: np.ndarray,
    image: np.ndarray,
    ranges: np.ndarray,
    proj_x: np.ndarray,
    proj_y: np.ndarray,
    knn: KnnSettings,
    num_classes: int,
    votes_from: int,
    *,
    threads: int | None = None,
    isa: int = 0,
) -> bool:
    """Write the classes of one scan's points that have a pixel into `result` (int64) with the
    compiled vote, on `threads` threads (default: torch's intra-op threads) in instruction set
    `isa` (0: the best); False, with nothing written, where it does not apply.

    `image` is the (H, W) range image (< 0 where empty), `classes` its (H, W) per-pixel classes,
    `ranges`, `proj_x`, `proj_y` the points' ranges and pixels (proj_x -1 for none).
    """
    if not result.size == ranges.size == len(proj_x) == len(proj_y):
        raise ValueError(
            f"one result, range and pixel per point: got {result.size} results, {ranges.size} "
            f"ranges, {len(proj_x)} proj_x and {len(proj_y)} proj_y"
        )
    if classes.shape != image.shape:
        raise ValueError(f"classes of shape {classes.shape} for a range image of {image.shape}")
    library = _library()
    wanted = knn.k - 1
    size = knn.search * knn.search - 1
    height, width = image.shape
    pad = knn.search // 2
    padded = (height + 2 * pad) * (width + 2 * pad)
    if library is None or min(wanted, size) > slots() or padded >= 2**31 or not ranges.size:
        return False
    ranges = np.ascontiguousarray(ranges, dtype=np.float32)
    # NaN distances have no order; an infinite point range meets the empty pixels' +inf in NaN
    if not (np.isfinite(ranges.min()) and np.isfinite(ranges.max())) or np.isnan(image.max()):
        return False
    far = np.zeros((height + 2 * pad, width + 2 * pad), dtype=np.float32)
    inside = far[pad : pad + height, pad : pad + width]
    np.copyto(inside, image)
    inside[image < 0] = np.inf
    codes = np.full(far.shape, padding_code(num_classes, votes_from), dtype=np.int32)
    inside = codes[pad : pad + height, pad : pad + width]
    np.subtract(num_classes + 1, classes.astype(np.int64, copy=False), out=inside, casting="unsafe")
    inside[classes < votes_from] = 0
    offsets, weights = _window(knn.search, knn.sigma, width + 2 * pad)
    proj_x = np.ascontiguousarray(proj_x, dtype=np.int64)
    proj_y = np.ascontiguousarray(proj_y, dtype=np.int64)
    cutoff = np.float32(knn.cutoff)
    use_cutoff = bool(knn.cutoff > 0)
    if not (result.dtype == np.int64 and result.flags.c_contiguous and result.flags.writeable):
        raise TypeError("result must be a writable contiguous int64 array")

    def part(start: int, stop: int) -> int:
        return library.rangeret_knn_vote(
            isa,
            far.ctypes.data,
            codes.ctypes.data,
            height,
            width,
            pad,
            offsets.ctypes.data,
            weights.ctypes.data,
            size,
            ranges.ctypes.data,
            proj_x.ctypes.data,
            proj_y.ctypes.data,
            start,
            stop,
            wanted,
            use_cutoff,
            cutoff,
            num_classes,
            votes_from,
            result.ctypes.data,
        )

    count = ranges.size
    threads = max(1, min(threads or torch.get_num_threads(), -(-count // _ALIGN)))
    step = -(-count // threads // _ALIGN) * _ALIGN
    bounds = [(start, min(start + step, count)) for start in range(0, count, step)]
    futures = [_Pool.get(len(bounds) - 1).submit(part, *b) for b in bounds[1:]]
    codes_back = [part(*bounds[0])] + [future.result() for future in futures]
    for code in codes_back:
        if code == -3:
            raise ValueError(
                f"a point's pixel lies outside the {height} x {width} range image "
                "(proj_x or proj_y out of range)"
            )
        if code:
            raise RuntimeError(f"the compiled kNN vote failed with code {code} (isa {isa})")
    return True
