"""Reading an archive's listing within bounds, before anything of it is held in memory.

A zip's end record (or zip64 end record) may not declare more than the member limit, and its
central directory is walked from the file header by header, counting, before `zipfile` reads it
(which builds every entry at once). A tar is read one header at a time by `CheckedTarFile`, whose
extended (pax, long-name) headers are bounded in size and number, since tarfile reads each into
memory, and whose sparse members are refused. `archive_kind` tells the formats apart by their
bytes. `service.archives.extraction` checks the members' names and extracts them; `ArchiveError` and
`ArchiveTooLarge` are the library's (`rangeret.dataset.upload_rules`).
"""

from __future__ import annotations

import os
import struct
import tarfile
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from rangeret.dataset.upload_rules import ArchiveError, ArchiveTooLarge

#: The zip end of central directory record, the zip64 locator and record, a central header.
_EOCD = struct.Struct("<4s4H2LH")
_ZIP64_LOCATOR = struct.Struct("<4sLQL")
_ZIP64_EOCD = struct.Struct("<4sQ2H2L4Q")
_CENTRAL = struct.Struct("<4s24x3H12x")  # signature, then the name, extra and comment lengths
_EOCD_SIGNATURE = b"PK\x05\x06"
_CENTRAL_SIGNATURE = b"PK\x01\x02"
#: Longest member name, in bytes: the layout's names are far shorter.
MAX_NAME = 1024
#: Largest tar extended (pax or long-name) header, and all global pax headers together.
_MAX_TAR_EXTENDED = 64 << 10
_MAX_TAR_GLOBAL = 4 << 10
_TAR_EXTENDED = (
    tarfile.GNUTYPE_LONGNAME,
    tarfile.GNUTYPE_LONGLINK,
    tarfile.XHDTYPE,
    tarfile.XGLTYPE,
    tarfile.SOLARIS_XHDTYPE,
)


def archive_kind(path: Path) -> str:
    """ "zip", "tar" or "tar.gz" from the file's bytes (never from its name): its first bytes, or
    for a zip with bytes prepended (as zipfile reads it), its end record."""
    with open(path, "rb") as f:
        head = f.read(512)
        if head[:4] in (b"PK\x03\x04", _EOCD_SIGNATURE):
            return "zip"
        if head[:2] == b"\x1f\x8b":
            return "tar.gz"
        if len(head) >= 262 and head[257:262] == b"ustar":
            return "tar"
        if _central_directory(f) is not None:
            return "zip"
    raise ArchiveError("The upload is not a .zip, .tar or .tar.gz archive.")


# Zip listing -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _CentralDirectory:
    """Where a zip's central directory lies, and how many entries its end record declares."""

    start: int
    size: int
    declared: int


def _central_directory(f: IO[bytes]) -> _CentralDirectory | None:
    """The central directory where zipfile finds it (the last end record, the zip64 one when a
    locator precedes it, the directory just before them, whatever bytes are prepended), or None
    when the file has no end record."""
    file_size = f.seek(0, os.SEEK_END)
    if file_size < _EOCD.size:
        return None
    tail_start = max(file_size - _EOCD.size - 0xFFFF, 0)
    f.seek(tail_start)
    tail = f.read()
    at = len(tail) - _EOCD.size
    if not (tail[at : at + 4] == _EOCD_SIGNATURE and tail[-2:] == b"\0\0"):
        at = tail.rfind(_EOCD_SIGNATURE)
        if at < 0 or at + _EOCD.size > len(tail):
            return None
    _, _, _, on_disk, total, size, offset, _ = _EOCD.unpack_from(tail, at)
    location = tail_start + at
    declared = max(on_disk, total)
    zip64 = _zip64_end(f, location)
    if zip64 is not None:
        location -= _ZIP64_LOCATOR.size + _ZIP64_EOCD.size
        declared, size, offset = zip64
    elif size == 0xFFFFFFFF or offset == 0xFFFFFFFF:
        raise ArchiveError(
            "The zip archive's end record points to a zip64 end record that it lacks; the archive "
            "is damaged."
        )
    if size > location:
        raise ArchiveError(
            f"The zip archive's central directory of {size:,} bytes would start before the file "
            "does; the archive is damaged."
        )
    return _CentralDirectory(start=location - size, size=size, declared=declared)


def _zip64_end(f: IO[bytes], location: int) -> tuple[int, int, int] | None:
    """The declared entries, size and offset of the central directory from the zip64 end record
    when a zip64 locator lies just before the end record at `location`, else None."""
    if location < _ZIP64_LOCATOR.size:
        return None
    f.seek(location - _ZIP64_LOCATOR.size)
    signature, disk, _, disks = _ZIP64_LOCATOR.unpack(f.read(_ZIP64_LOCATOR.size))
    if signature != b"PK\x06\x07":
        return None
    if disk != 0 or disks > 1:
        raise ArchiveError("The zip archive spans several disks, and those are refused.")
    start = location - _ZIP64_LOCATOR.size - _ZIP64_EOCD.size
    if start < 0:
        raise ArchiveError("The zip archive's zip64 end record is missing; the archive is damaged.")
    f.seek(start)
    fields = _ZIP64_EOCD.unpack(f.read(_ZIP64_EOCD.size))
    if fields[0] != b"PK\x06\x06":
        return None
    on_disk, total, size, offset = fields[6:]
    return max(on_disk, total), size, offset


def count_zip_entries(path: Path, max_members: int) -> int:
    """The zip's entry count, walking its central directory from the file header by header, so
    that zipfile reads no more than `max_members` entries: 413 as soon as the declared or the
    walked count passes it, 400 for a damaged directory or a name with a NUL byte (checked on its
    raw bytes, which zipfile would cut at the NUL)."""
    with open(path, "rb", buffering=1 << 16) as f:
        directory = _central_directory(f)
        if directory is None:
            raise ArchiveError(
                "The zip archive has no end of central directory record; it is damaged or truncated."
            )
        if directory.declared > max_members:
            raise ArchiveTooLarge(
                f"The archive declares {directory.declared:,} members, more than the limit of "
                f"{max_members:,} (files and folders)."
            )
        f.seek(directory.start)
        end = directory.start + directory.size
        pos, count = directory.start, 0
        while pos < end:
            header = f.read(_CENTRAL.size)
            if len(header) != _CENTRAL.size or pos + _CENTRAL.size > end:
                raise ArchiveError(
                    f"The zip archive's central directory is truncated at entry {count + 1:,}."
                )
            signature, name, extra, comment = _CENTRAL.unpack(header)
            if signature != _CENTRAL_SIGNATURE:
                raise ArchiveError(
                    f"Entry {count + 1:,} of the zip archive's central directory has no header "
                    "signature; the archive is damaged."
                )
            count += 1
            if count > max_members:
                raise ArchiveTooLarge(too_many_members(max_members))
            if name > MAX_NAME:
                raise ArchiveError(
                    f"Entry {count:,} of the zip archive has a name of {name:,} bytes, longer than "
                    f"the {MAX_NAME:,} allowed."
                )
            pos += _CENTRAL.size + name + extra + comment
            if pos > end:
                raise ArchiveError(
                    f"Entry {count:,} of the zip archive's central directory runs past its end; "
                    "the archive is damaged."
                )
            raw = f.read(name)
            if b"\0" in raw:  # zipfile would cut the name there, before any check sees the rest
                shown = raw.split(b"\0", 1)[0].decode("utf-8", "replace")[:200]
                raise ArchiveError(
                    f"Entry {count:,} of the zip archive ({shown!r}) has a NUL byte in its name."
                )
            f.seek(extra + comment, os.SEEK_CUR)
    return count


def too_many_members(max_members: int) -> str:
    """The answer to an archive of more than `max_members` entries."""
    return f"The archive holds more than the limit of {max_members:,} members (files and folders)."


# Tar listing -------------------------------------------------------------------------------------


@dataclass
class TarHeaders:
    """The extended tar headers read so far, bounded since tarfile reads each one into memory."""

    max_count: int
    count: int = 0
    global_bytes: int = 0


class _CheckedTarInfo(tarfile.TarInfo):
    """A tar header that refuses sparse files and extended headers over their bounds before
    tarfile reads them."""

    def _proc_member(self, archive: tarfile.TarFile) -> tarfile.TarInfo:
        """Check the header against the archive's bounds, then process it as tarfile does."""
        if self.type == tarfile.GNUTYPE_SPARSE:
            raise ArchiveError(sparse_member(self.name))
        if self.type in _TAR_EXTENDED:
            headers: TarHeaders = archive.extended_headers  # type: ignore[attr-defined]
            headers.count += 1
            if headers.count > headers.max_count:
                raise ArchiveTooLarge(
                    f"The archive holds more than {headers.max_count:,} extended (pax or "
                    "long-name) headers."
                )
            if self.size > _MAX_TAR_EXTENDED:
                raise ArchiveError(
                    f"The archive holds an extended header of {self.size:,} bytes, more than the "
                    f"{_MAX_TAR_EXTENDED:,} allowed."
                )
            if self.type == tarfile.XGLTYPE:
                headers.global_bytes += self.size
                if headers.global_bytes > _MAX_TAR_GLOBAL:
                    raise ArchiveError(
                        f"The archive's global extended headers hold more than the "
                        f"{_MAX_TAR_GLOBAL:,} bytes allowed."
                    )
        return super()._proc_member(archive)

    def _proc_gnusparse_10(
        self, next: tarfile.TarInfo, pax_headers: dict[str, str], archive: tarfile.TarFile
    ) -> None:
        """Refuse a sparse file before tarfile reads its map, of any length, into memory."""
        raise ArchiveError(sparse_member(next.name))


class CheckedTarFile(tarfile.TarFile):
    """A tar reader of `_CheckedTarInfo` headers, whose extended headers share one bound."""

    tarinfo = _CheckedTarInfo

    def __init__(self, *args: Any, extended_headers: TarHeaders, **kwargs: Any) -> None:
        self.extended_headers = extended_headers
        super().__init__(*args, **kwargs)


def sparse_member(name: str) -> str:
    """The answer to a sparse tar member."""
    return f"Archive member {name[:200]!r} is a sparse file, and those are refused."
