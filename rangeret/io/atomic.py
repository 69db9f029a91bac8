"""Atomic file writes: a reader never sees a half-written file, and a failed write leaves none.

Every file the project writes for others to read (labels, scans, checkpoints, archives, run
records) goes through `atomic_path`: the content is written to a temporary file in the target's
folder and renamed over the target only when the writer finishes without an error.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str], suffix: str = ".tmp") -> Iterator[Path]:
    """Yield a temporary path beside `path`; on a clean exit it replaces `path`, else it is removed.

    The body may write the temporary file by any means (a zip writer, torch.save, a check of the
    finished file); raising inside the body keeps the previous `path` untouched. The temporary
    name is hidden and ends with `suffix` (".tmp", so no reader's pattern matches a leftover,
    unless a check of the finished file needs the real extension).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        # mkstemp creates the file readable by its owner only; give it the mode a plain open()
        # would have (0666 less the umask), so others may read what the project writes.
        if tmp.exists():
            os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _read_umask() -> int:
    """The process's file-creation mask, read once at import (reading it means setting it and
    setting it back, which other threads must not see)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


_UMASK = _read_umask()


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes | memoryview) -> None:
    """Write `data` to `path` atomically."""
    view = memoryview(data)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(view)


def atomic_write_text(path: str | os.PathLike[str], text: str) -> None:
    """Write UTF-8 `text` to `path` atomically."""
    atomic_write_bytes(path, text.encode("utf-8"))
