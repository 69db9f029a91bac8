"""Reproducible zip archives: the same entries give the same bytes, whenever and wherever written.

Entries carry a fixed timestamp and fixed permissions, directories are explicit entries (the
benchmark server wants them), and files are deflated at one fixed level. Submission archives and
the gateway's prediction archives are both written with `ReproducibleZip`.

Deflating is the slow part of writing a large archive, so files can be deflated ahead in a thread
pool (zlib releases the GIL) and written in order: `deflate_file` gives the very stream
`zipfile` writes (raw deflate, level 6, 32 KiB window, default memLevel), whichever thread runs
it, so an archive is byte-for-byte the same for any number of workers. The central directory and
the end records are `zipfile`'s own, so ZIP64 records appear as `zipfile` writes them: for a
member or an offset over 2 GiB, and for more than 65,535 entries.
"""

from __future__ import annotations

import os
import stat
import zipfile
import zlib
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from types import TracebackType
from typing import TypeVar

#: The earliest time a zip can record; every entry carries it.
ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)
_COMPRESS_LEVEL = 6
#: Tasks in flight per worker in `map_ahead`: enough to keep every worker busy while the caller
#: writes, few enough that memory stays bounded.
_AHEAD_PER_WORKER = 2

T = TypeVar("T")
R = TypeVar("R")


def available_cpus() -> int:
    """The CPUs this process may run on (its affinity where the platform tells it)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def map_ahead(fn: Callable[[T], R], items: Iterable[T], workers: int | None = None) -> Iterator[R]:
    """`fn` over `items` in `workers` threads (default: `available_cpus()`), results in order.

    At most `2 * workers` items are taken from `items` and not yet yielded at any time, so memory
    stays bounded however many there are; with one worker everything runs in the caller's thread.
    An exception in `fn` is raised where its result would be yielded, and the tasks not yet
    started are cancelled.
    """
    workers = available_cpus() if workers is None else workers
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    return map(fn, items) if workers == 1 else _threaded_map(fn, items, workers)


def _threaded_map(fn: Callable[[T], R], items: Iterable[T], workers: int) -> Iterator[R]:
    pending: deque[Future[R]] = deque()
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="rangeret-ahead") as pool:
        try:
            for item in items:
                pending.append(pool.submit(fn, item))
                if len(pending) >= _AHEAD_PER_WORKER * workers:
                    yield pending.popleft().result()
            while pending:
                yield pending.popleft().result()
        finally:
            for future in pending:
                future.cancel()


@dataclass(frozen=True)
class DeflatedFile:
    """A file entry's name, its deflated bytes, and the CRC-32 and size of its contents."""

    name: str
    data: bytes
    crc: int
    size: int


def deflate_file(name: str, data: bytes | str) -> DeflatedFile:
    """Deflate `data` (text as UTF-8) exactly as `ZipFile.writestr` does at level 6; thread-safe."""
    if isinstance(data, str):
        data = data.encode("utf-8")
    compressor = zlib.compressobj(_COMPRESS_LEVEL, zlib.DEFLATED, -15)
    deflated = compressor.compress(data) + compressor.flush()
    return DeflatedFile(name=name, data=deflated, crc=zlib.crc32(data), size=len(data))


def _append_deflated(zf: zipfile.ZipFile, info: zipfile.ZipInfo, file: DeflatedFile) -> None:
    """Write an entry deflated beforehand: its local header, then its data, as `writestr` would.

    `zipfile` has no public way to store data deflated elsewhere, so this is the one place that
    uses its internals (`fp`, `start_dir`, `_writecheck`, `_didModify`, `filelist`,
    `NameToInfo`). It follows `ZipFile._open_to_write` and `_ZipWriteFile.close` for a seekable
    file with ZIP64 allowed, knowing the sizes and CRC before the header instead of seeking back;
    the tests compare its archives with `writestr`'s byte for byte.
    """
    info.file_size = file.size
    info.compress_size = len(file.data)
    info.CRC = file.crc
    info.flag_bits = 0
    # zipfile's rule, made before it compresses: the size with a 5 % margin. Deflate never grows
    # data that much, so also checking the compressed size (known here) changes no archive.
    limit = zipfile.ZIP64_LIMIT
    zip64 = info.file_size * 1.05 > limit or info.compress_size > limit
    zf._writecheck(info)
    zf._didModify = True
    zf.fp.seek(zf.start_dir)
    info.header_offset = zf.fp.tell()
    zf.fp.write(info.FileHeader(zip64))
    zf.fp.write(file.data)
    zf.start_dir = zf.fp.tell()
    zf.filelist.append(info)
    zf.NameToInfo[info.filename] = info


class ReproducibleZip:
    """A zip file opened for writing whose entries depend only on their names and contents."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self._zip = zipfile.ZipFile(
            path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=_COMPRESS_LEVEL
        )

    def add_directory(self, name: str) -> None:
        """An explicit directory entry; `name` ends with '/'."""
        if not name.endswith("/"):
            raise ValueError(f"a directory entry ends with '/', got {name!r}")
        info = zipfile.ZipInfo(name, date_time=ZIP_EPOCH)
        info.external_attr = (stat.S_IFDIR | 0o755) << 16 | 0x10
        info.compress_type = zipfile.ZIP_STORED
        self._zip.writestr(info, b"")

    def add_file(self, name: str, data: bytes | str) -> None:
        """A regular file entry holding `data` (text is written as UTF-8), deflated here."""
        self.add_deflated(deflate_file(name, data))

    def add_deflated(self, file: DeflatedFile) -> None:
        """A regular file entry from `deflate_file`, which may have run in any thread."""
        info = zipfile.ZipInfo(file.name, date_time=ZIP_EPOCH)
        info.external_attr = (stat.S_IFREG | 0o644) << 16
        info.compress_type = zipfile.ZIP_DEFLATED
        _append_deflated(self._zip, info, file)

    def add_files(
        self, files: Iterable[tuple[str, Callable[[], bytes | str]]], workers: int | None = None
    ) -> None:
        """File entries in the order given, each read by its loader and deflated in `workers`
        threads (default: every available CPU), at most `2 * workers` files held at once."""

        def load(item: tuple[str, Callable[[], bytes | str]]) -> DeflatedFile:
            return deflate_file(item[0], item[1]())

        for file in map_ahead(load, files, workers):
            self.add_deflated(file)

    def close(self) -> None:
        """Write the central directory and close the file."""
        self._zip.close()

    def __enter__(self) -> ReproducibleZip:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
