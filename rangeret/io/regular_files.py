"""Files a command reads whole are regular files: anything else is refused by its kind first.

A FIFO blocks whoever opens it until a writer comes, `/dev/zero` never ends, a folder has no
bytes: none of them is a table, a checkpoint or a scan. `open_regular` opens without blocking
(so a FIFO cannot stall it), asks the open file what it is and refuses anything but a regular
file in one sentence naming the path and its kind, before a byte is read.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import BinaryIO

from rangeret.exceptions import InputError, InputFileMissing

#: What each kind of file that is not a regular one is called in a refusal.
_KINDS = (
    (stat.S_ISDIR, "a folder"),
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


class NotRegularFileError(InputError, ValueError):
    """A path that names something other than a regular file where one is read; `kind` says
    what it is (`a folder`, `a FIFO (named pipe)`, ...)."""

    def __init__(self, message: str, kind: str = "not a regular file") -> None:
        super().__init__(message)
        self.kind = kind


class FileTooLargeError(InputError, ValueError):
    """A file larger than what may be read of its kind."""


def file_kind(mode: int) -> str:
    """What a file of `mode` (st_mode) is, in words: `a folder`, `a FIFO (named pipe)`, ..."""
    for test, name in _KINDS:
        if test(mode):
            return name
    return "a regular file" if stat.S_ISREG(mode) else "not a regular file"


def refusal(path: Path | str, mode: int, what: str) -> str:
    """The sentence that refuses `path` of `mode` where `what` (a table, a checkpoint) is read."""
    return f"{path} is {file_kind(mode)}, not a file: {what} must be a regular file"


def require_regular(path: Path | str, what: str) -> os.stat_result:
    """The stat of `path` (links followed) when it is a regular file, else
    `NotRegularFileError`; `InputFileMissing` when there is nothing there. Opens nothing."""
    try:
        info = os.stat(path)
    except FileNotFoundError as exc:
        raise InputFileMissing.of(exc) from exc
    if not stat.S_ISREG(info.st_mode):
        raise NotRegularFileError(refusal(path, info.st_mode, what), file_kind(info.st_mode))
    return info


def open_regular(path: Path | str, what: str) -> BinaryIO:
    """`path` opened for reading in binary mode, if it is a regular file (judged on the open file
    itself, after an open that cannot block); else `NotRegularFileError` naming it and its kind,
    `InputFileMissing` when there is nothing there."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except FileNotFoundError as exc:
        raise InputFileMissing.of(exc) from exc
    except OSError as exc:  # a socket cannot be opened at all
        try:
            mode = os.stat(path).st_mode
        except OSError:
            raise exc from None
        if stat.S_ISREG(mode):  # a file that may not be read (permissions): the error as it is
            raise
        raise NotRegularFileError(refusal(path, mode, what), file_kind(mode)) from exc
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise NotRegularFileError(refusal(path, mode, what), file_kind(mode))
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_regular(path: Path | str, what: str, limit: int | None = None) -> bytes:
    """The bytes of the regular file `path` (see `open_regular`); with `limit`, a file larger
    than `limit` bytes is a `FileTooLargeError` before a byte of it is read."""
    with open_regular(path, what) as f:
        size = os.fstat(f.fileno()).st_size
        if limit is not None and size > limit:
            raise FileTooLargeError(
                f"{path} is {size:,} bytes, more than the {limit:,} that {what} may have"
            )
        return f.read()
