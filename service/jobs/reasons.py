"""The one-line reasons a failed job is stored with, free of the server's own paths.

A client reads a job's `reason` and `errors`: they name files by their place in the job's folder
or under a data root, never by the server's absolute paths, and carry no raw errno text.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

#: The `[Errno N] ` that OS errors put before their reason.
_ERRNO = re.compile(r"\[Errno \d+\] ")
#: The longest reason kept.
MAX_REASON = 500


def failure_sentence(exc: BaseException, folder: Path | None = None) -> str:
    """One readable line for an exception: an OS error as its reason and the path within the
    job's `folder` (never the server's absolute paths nor raw errno text)."""
    if isinstance(exc, OSError) and exc.strerror:
        where = ""
        if exc.filename is not None:
            name = Path(str(exc.filename))
            inside = folder is not None and name.is_relative_to(folder)
            where = f": {name.relative_to(folder).as_posix()}" if inside else f": {name.name}"
        return f"{exc.strerror.lower()}{where}"[:MAX_REASON]
    return scrub(" ".join(str(exc).split()) or type(exc).__name__, folder)[:MAX_REASON]


def scrub(text: str, folder: Path | None, roots: Sequence[Path] | None = None) -> str:
    """`text` with the job's folder and the data roots made relative (the server's own paths
    are not the client's business) and raw errno text dropped."""
    if folder is not None:
        text = text.replace(str(folder) + "/", "").replace(str(folder), "the job's folder")
    for root in roots or ():
        text = text.replace(str(root).rstrip("/") + "/", "")
    return _ERRNO.sub("", text)
