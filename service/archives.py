"""Safe extraction of uploaded sequence archives (.zip, .tar, .tar.gz) into a job's folder.

Every entry counts against `max_members`, folders included, and is counted as the archive is
listed, before its listing is held in memory: a zip's end record (or zip64 end record) may not
declare more, and its central directory is then walked from the file, header by header, before
`zipfile` reads it; a tar is read one header at a time, and its extended (pax, long-name) headers
are bounded too. The files' declared sizes may add up to at most `max_extracted_bytes`, checked
before anything is written and again on the bytes actually read; there is no compression-ratio
rule, since a label file of one class compresses like a bomb of zeros. `max_bytes` bounds the
archive file itself.

Every member is checked before anything is written: no absolute path, no `..`, no link, device,
pipe or sparse file, nothing but `sequences/XX/velodyne/NNNNNN.bin` and
`sequences/XX/labels/NNNNNN.label` (and their folders), whatever the dataset profile. Then each
file is read (never more than its declared size), checked as a scan of the profile's point record
or a label file, and written under the destination in the profile's folder layout, with names
built from the checked parts only.
"""

from __future__ import annotations

import gzip
import os
import re
import stat
import struct
import tarfile
import zipfile
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from rangeret.io import KITTI_RECORD, LABEL_BYTES, PointRecord, ScanFormatError, parse_scan
from rangeret.layout import KITTI_LAYOUT, SequenceLayout, sequence_dir

_DIRECTORY = re.compile(r"^sequences(/[A-Za-z0-9_-]{1,64}(/(velodyne|labels))?)?/?$")
_FILE = re.compile(
    r"^sequences/([A-Za-z0-9_-]{1,64})/(velodyne|labels)/([A-Za-z0-9_-]{1,64})\.(bin|label)$"
)
_SUFFIX = {"velodyne": "bin", "labels": "label"}
_CHUNK = 1 << 20

#: The zip end of central directory record, the zip64 locator and record, a central header.
_EOCD = struct.Struct("<4s4H2LH")
_ZIP64_LOCATOR = struct.Struct("<4sLQL")
_ZIP64_EOCD = struct.Struct("<4sQ2H2L4Q")
_CENTRAL = struct.Struct("<4s24x3H12x")  # signature, then the name, extra and comment lengths
_EOCD_SIGNATURE = b"PK\x05\x06"
_CENTRAL_SIGNATURE = b"PK\x01\x02"
#: Longest member name, in bytes: the layout's names are far shorter.
_MAX_NAME = 1024
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


class ArchiveError(ValueError):
    """An upload that is not a safe archive in the expected layout (answered with 400)."""

    status_code = 400


class ArchiveTooLarge(ArchiveError):
    """An archive over the member-count, size, extracted-size or points limits (answered with
    413)."""

    status_code = 413


@dataclass(frozen=True)
class ArchiveLimits:
    """Limits on what one archive may hold: its own size, its entries (folders included), each
    file's points and its files' total size once extracted."""

    max_bytes: int
    max_members: int
    max_points: int
    max_extracted_bytes: int


@dataclass
class ExtractedDataset:
    """The dataset an archive held: where it now lies and what it contains."""

    root: Path
    sequences: list[str]
    scans: int
    labelled: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class _Member:
    name: str
    size: int
    is_dir: bool
    handle: object


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


def _count_zip_entries(path: Path, max_members: int) -> int:
    """The zip's entry count, walking its central directory from the file header by header, so
    that zipfile reads no more than `max_members` entries: 413 as soon as the declared or the
    walked count passes it, 400 for a damaged directory."""
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
                raise ArchiveTooLarge(_too_many(max_members))
            if name > _MAX_NAME:
                raise ArchiveError(
                    f"Entry {count:,} of the zip archive has a name of {name:,} bytes, longer than "
                    f"the {_MAX_NAME:,} allowed."
                )
            pos += _CENTRAL.size + name + extra + comment
            if pos > end:
                raise ArchiveError(
                    f"Entry {count:,} of the zip archive's central directory runs past its end; "
                    "the archive is damaged."
                )
            f.seek(name + extra + comment, os.SEEK_CUR)
    return count


def _too_many(max_members: int) -> str:
    """The answer to an archive of more than `max_members` entries."""
    return f"The archive holds more than the limit of {max_members:,} members (files and folders)."


# Tar listing -------------------------------------------------------------------------------------


@dataclass
class _TarHeaders:
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
            raise ArchiveError(_sparse(self.name))
        if self.type in _TAR_EXTENDED:
            headers: _TarHeaders = archive.extended_headers  # type: ignore[attr-defined]
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
        raise ArchiveError(_sparse(next.name))


class _CheckedTarFile(tarfile.TarFile):
    """A tar reader of `_CheckedTarInfo` headers, whose extended headers share one bound."""

    tarinfo = _CheckedTarInfo

    def __init__(self, *args: Any, extended_headers: _TarHeaders, **kwargs: Any) -> None:
        self.extended_headers = extended_headers
        super().__init__(*args, **kwargs)


def _sparse(name: str) -> str:
    """The answer to a sparse tar member."""
    return f"Archive member {name[:200]!r} is a sparse file, and those are refused."


def _escape_problem(name: str) -> str | None:
    """Why a member name could land outside the destination, or None."""
    if not name or "\x00" in name:
        return "has an empty or invalid name"
    if name.startswith(("/", "\\")) or re.match(r"^[A-Za-z]:", name):
        return "has an absolute path"
    if ".." in re.split(r"[/\\]", name):
        return "contains '..'"
    if "\\" in name:
        return "has a Windows path"
    return None


def _clean(name: str) -> str:
    while name.startswith("./"):
        name = name[2:]
    return name


def _check_name(raw: str, is_dir: bool) -> str:
    """The member's checked name, or ArchiveError saying why it is refused."""
    if len(raw) > _MAX_NAME:
        raise ArchiveError(
            f"Archive member {raw[:200]!r}... has a name of {len(raw):,} characters, longer than "
            f"the {_MAX_NAME:,} allowed."
        )
    problem = _escape_problem(raw)
    if problem:
        raise ArchiveError(
            f"Archive member {raw[:200]!r} {problem} and would escape the job folder."
        )
    name = _clean(raw)
    if is_dir:
        if name in ("", ".") or _DIRECTORY.match(name):
            return name
        raise ArchiveError(
            f"Archive member {name[:200]!r} is a folder outside the layout sequences/XX/velodyne|labels."
        )
    match = _FILE.match(name)
    if not match or _SUFFIX[match.group(2)] != match.group(4):
        raise ArchiveError(
            f"Archive member {name[:200]!r} is not a sequences/XX/velodyne/*.bin scan or "
            "sequences/XX/labels/*.label file."
        )
    return name


def _zip_members(zf: zipfile.ZipFile) -> Iterator[_Member]:
    for info in zf.infolist():
        kind = stat.S_IFMT(info.external_attr >> 16)
        if kind == stat.S_IFLNK:
            raise ArchiveError(
                f"Archive member {info.filename[:200]!r} is a link, and links are refused."
            )
        if kind and kind not in (stat.S_IFREG, stat.S_IFDIR):
            raise ArchiveError(
                f"Archive member {info.filename[:200]!r} is a device or special file, and those are refused."
            )
        if info.flag_bits & 0x1:
            raise ArchiveError(f"Archive member {info.filename[:200]!r} is encrypted.")
        yield _Member(info.filename, info.file_size, info.is_dir(), info)


def _tar_members(tf: tarfile.TarFile) -> Iterator[_Member]:
    """The tar's members one header at a time, as they are read (never the whole listing)."""
    while (info := tf.next()) is not None:
        info.pax_headers = {}  # applied already; kept, they would hold memory for every member
        if info.issym() or info.islnk():
            raise ArchiveError(
                f"Archive member {info.name[:200]!r} is a link, and links are refused."
            )
        if info.ischr() or info.isblk() or info.isfifo():
            raise ArchiveError(
                f"Archive member {info.name[:200]!r} is a device or pipe, and those are refused."
            )
        if getattr(info, "sparse", None) is not None:
            raise ArchiveError(_sparse(info.name))
        if not (info.isfile() or info.isdir()):
            raise ArchiveError(f"Archive member {info.name[:200]!r} is not a plain file or folder.")
        yield _Member(info.name, info.size, info.isdir(), info)


def extract_archive(
    archive: Path,
    dest: Path,
    limits: ArchiveLimits,
    record: PointRecord = KITTI_RECORD,
    layout: SequenceLayout = KITTI_LAYOUT,
) -> ExtractedDataset:
    """Check every member of `archive` (scans as `record`s), then write its scans and labels
    under `dest` in `layout`, so the dataset there reads like any other of its profile."""
    size = archive.stat().st_size
    if size > limits.max_bytes:
        raise ArchiveTooLarge(
            f"The archive is {size:,} bytes, more than the limit of {limits.max_bytes:,}."
        )
    kind = archive_kind(archive)
    try:
        if kind == "zip":
            entries = _count_zip_entries(archive, limits.max_members)
            with zipfile.ZipFile(archive) as zf:
                if len(zf.filelist) != entries:
                    raise ArchiveError(
                        f"The zip archive lists {len(zf.filelist):,} entries where its central "
                        f"directory holds {entries:,}; the archive is damaged."
                    )
                members = _listing(_zip_members(zf), limits, record)
                return _extract(members, dest, limits, record, layout, lambda m: zf.open(m.handle))
        headers = _TarHeaders(max_count=limits.max_members)
        mode = "r:gz" if kind == "tar.gz" else "r:"
        with _CheckedTarFile.open(archive, mode, extended_headers=headers) as tf:
            members = _listing(_tar_members(tf), limits, record)
            return _extract(
                members, dest, limits, record, layout, lambda m: tf.extractfile(m.handle)
            )
    except (
        zipfile.BadZipFile,
        tarfile.TarError,
        gzip.BadGzipFile,
        zlib.error,
        EOFError,
        NotImplementedError,
    ) as exc:
        raise ArchiveError(
            f"The {kind} archive is damaged or uses an unsupported feature ({exc})."
        ) from exc


def _listing(found: Iterator[_Member], limits: ArchiveLimits, record: PointRecord) -> list[_Member]:
    """Every member, checked for names, kinds, duplicates and the limits as it is listed (each
    entry counted, folders too, and the files' declared sizes added up), before any write."""
    members: list[_Member] = []
    names: set[str] = set()
    total = 0
    for seen, member in enumerate(found, start=1):
        if seen > limits.max_members:
            raise ArchiveTooLarge(_too_many(limits.max_members))
        name = _check_name(member.name, member.is_dir)
        if member.is_dir:
            continue
        if name in names:
            raise ArchiveError(f"Archive member {name!r} appears more than once.")
        names.add(name)
        total += member.size
        if total > limits.max_extracted_bytes:
            raise ArchiveTooLarge(_too_big(limits.max_extracted_bytes))
        per_point = record.point_bytes if name.endswith(".bin") else LABEL_BYTES
        if member.size > limits.max_points * per_point:
            raise ArchiveTooLarge(
                f"Archive member {name!r} holds more than {limits.max_points:,} points."
            )
        members.append(_Member(name, member.size, False, member.handle))
    return members


def _too_big(max_extracted_bytes: int) -> str:
    """The answer to an archive whose files add up to more than `max_extracted_bytes`."""
    return f"The archive's files add up to more than {max_extracted_bytes:,} bytes once extracted."


def _extract(
    members: list[_Member],
    dest: Path,
    limits: ArchiveLimits,
    record: PointRecord,
    layout: SequenceLayout,
    opener: Callable[[_Member], IO[bytes] | None],
) -> ExtractedDataset:
    """Read, check and write each file member into `layout`, counting the bytes actually read
    against the extracted limit; then check scans and labels match up."""
    scans: dict[str, dict[str, int]] = {}
    labels: dict[str, dict[str, int]] = {}
    dest.mkdir(parents=True, exist_ok=True)
    root = dest.resolve()
    extracted = 0
    for member in members:
        seq, folder, stem, _ = _FILE.match(member.name).groups()
        stream = opener(member)
        if stream is None:
            raise ArchiveError(f"Archive member {member.name!r} cannot be read.")
        with stream:
            data = stream.read(member.size + 1)
        extracted += len(data)
        if extracted > limits.max_extracted_bytes:
            raise ArchiveTooLarge(_too_big(limits.max_extracted_bytes))
        if len(data) != member.size:
            raise ArchiveError(
                f"Archive member {member.name!r} does not hold the {member.size} bytes it declares."
            )
        if folder == "velodyne":
            try:
                points = parse_scan(data, member.name, record)
            except ScanFormatError as exc:
                raise ArchiveError(f"Archive member {exc.source}: {exc.problem}.") from exc
            scans.setdefault(seq, {})[stem] = len(points)
        else:
            if len(data) % LABEL_BYTES:
                raise ArchiveError(
                    f"Archive member {member.name!r} is {len(data)} bytes, not a whole number of uint32 labels."
                )
            labels.setdefault(seq, {})[stem] = len(data) // LABEL_BYTES
        target = sequence_dir(root, seq, layout) / folder / f"{stem}.{_SUFFIX[folder]}"
        if not target.resolve().is_relative_to(root):
            raise ArchiveError(f"Archive member {member.name!r} would escape the job folder.")
        target.parent.mkdir(parents=True, exist_ok=True)
        with open(target, "xb") as out:
            out.write(data)
    return _summarise(root, scans, labels)


def _summarise(
    root: Path, scans: dict[str, dict[str, int]], labels: dict[str, dict[str, int]]
) -> ExtractedDataset:
    """The extracted dataset, once every label file is known to match a scan of its length."""
    if not scans:
        raise ArchiveError("The archive holds no scan under sequences/XX/velodyne/.")
    for seq, found in labels.items():
        have = scans.get(seq, {})
        for stem, count in sorted(found.items()):
            if stem not in have:
                raise ArchiveError(
                    f"Label file sequences/{seq}/labels/{stem}.label has no matching scan."
                )
            if count != have[stem]:
                raise ArchiveError(
                    f"Label file sequences/{seq}/labels/{stem}.label holds {count} labels but its scan "
                    f"has {have[stem]} points."
                )
        missing = sorted(set(have) - set(found))
        if missing:
            raise ArchiveError(
                f"Sequence {seq} has labels for some scans but not for {len(missing)} of them "
                f"(the first: {missing[0]}.bin)."
            )
    return ExtractedDataset(
        root=root,
        sequences=sorted(scans),
        scans=sum(len(v) for v in scans.values()),
        labelled=sorted(labels),
    )
