"""Reproducible zip archives: the same entries give the same bytes, whenever and wherever written.

Entries carry a fixed timestamp and fixed permissions, directories are explicit entries (the
benchmark server wants them), and files are deflated at one fixed level. Submission archives and
the gateway's prediction archives are both written with `ReproducibleZip`.
"""

from __future__ import annotations

import os
import stat
import zipfile
from types import TracebackType

#: The earliest time a zip can record; every entry carries it.
ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)
_COMPRESS_LEVEL = 6


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
        """A regular file entry holding `data` (text is written as UTF-8)."""
        info = zipfile.ZipInfo(name, date_time=ZIP_EPOCH)
        info.external_attr = (stat.S_IFREG | 0o644) << 16
        info.compress_type = zipfile.ZIP_DEFLATED
        self._zip.writestr(info, data, compresslevel=_COMPRESS_LEVEL)

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
