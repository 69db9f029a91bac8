"""Safe extraction of uploaded sequence archives (.zip, .tar, .tar.gz) into a job's folder.

Every member is checked before anything is written: no absolute path, no `..`, no link, device
or pipe, nothing but `sequences/XX/velodyne/NNNNNN.bin` and `sequences/XX/labels/NNNNNN.label`
(and their folders), whatever the dataset profile; at most `max_members` members and `max_bytes`
bytes in all. Then each file is read (never more than its declared size), checked as a scan of
the profile's point record or a label file, and written under the destination in the profile's
folder layout, with names built from the checked parts only.
"""

from __future__ import annotations

import gzip
import re
import stat
import tarfile
import zipfile
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

from rangeret.io import KITTI_RECORD, LABEL_BYTES, PointRecord, ScanFormatError, parse_scan
from rangeret.layout import KITTI_LAYOUT, SequenceLayout, sequence_dir

_DIRECTORY = re.compile(r"^sequences(/[A-Za-z0-9_-]{1,64}(/(velodyne|labels))?)?/?$")
_FILE = re.compile(
    r"^sequences/([A-Za-z0-9_-]{1,64})/(velodyne|labels)/([A-Za-z0-9_-]{1,64})\.(bin|label)$"
)
_SUFFIX = {"velodyne": "bin", "labels": "label"}
_CHUNK = 1 << 20


class ArchiveError(ValueError):
    """An upload that is not a safe archive in the expected layout (answered with 400)."""

    status_code = 400


class ArchiveTooLarge(ArchiveError):
    """An archive over the member-count, size or points limits (answered with 413)."""

    status_code = 413


@dataclass(frozen=True)
class ArchiveLimits:
    """Limits on what one archive may hold."""

    max_bytes: int
    max_members: int
    max_points: int


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
    """ "zip", "tar" or "tar.gz" from the file's first bytes (never from its name)."""
    with open(path, "rb") as f:
        head = f.read(512)
    if head[:4] in (b"PK\x03\x04", b"PK\x05\x06"):
        return "zip"
    if head[:2] == b"\x1f\x8b":
        return "tar.gz"
    if len(head) >= 262 and head[257:262] == b"ustar":
        return "tar"
    raise ArchiveError("The upload is not a .zip, .tar or .tar.gz archive.")


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
    for info in tf:
        if info.issym() or info.islnk():
            raise ArchiveError(
                f"Archive member {info.name[:200]!r} is a link, and links are refused."
            )
        if info.ischr() or info.isblk() or info.isfifo():
            raise ArchiveError(
                f"Archive member {info.name[:200]!r} is a device or pipe, and those are refused."
            )
        if not (info.isfile() or info.isdir()):
            raise ArchiveError(f"Archive member {info.name[:200]!r} is not a plain file or folder.")
        yield _Member(info.name, info.size, info.isdir(), info)


def _read_limited(stream: IO[bytes], size: int, name: str) -> bytes:
    """A member's bytes, refusing a member that holds more than it declared."""
    data = stream.read(size + 1)
    if len(data) != size:
        raise ArchiveError(f"Archive member {name!r} does not hold the {size} bytes it declares.")
    return data


def extract_archive(
    archive: Path,
    dest: Path,
    limits: ArchiveLimits,
    record: PointRecord = KITTI_RECORD,
    layout: SequenceLayout = KITTI_LAYOUT,
) -> ExtractedDataset:
    """Check every member of `archive` (scans as `record`s), then write its scans and labels
    under `dest` in `layout`, so the dataset there reads like any other of its profile."""
    kind = archive_kind(archive)
    try:
        if kind == "zip":
            with zipfile.ZipFile(archive) as zf:
                members = _listing(_zip_members(zf), limits, record)
                return _extract(members, dest, record, layout, lambda m: zf.open(m.handle))
        with tarfile.open(archive, "r:gz" if kind == "tar.gz" else "r:") as tf:
            members = _listing(_tar_members(tf), limits, record)
            return _extract(members, dest, record, layout, lambda m: tf.extractfile(m.handle))
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
    """Every member, checked for names, kinds, duplicates and the limits, before any write."""
    members: list[_Member] = []
    names: set[str] = set()
    total = 0
    for member in found:
        if len(members) >= limits.max_members:
            raise ArchiveTooLarge(f"The archive holds more than {limits.max_members:,} members.")
        name = _check_name(member.name, member.is_dir)
        if member.is_dir:
            continue
        if name in names:
            raise ArchiveError(f"Archive member {name!r} appears more than once.")
        names.add(name)
        total += member.size
        if total > limits.max_bytes:
            raise ArchiveTooLarge(
                f"The archive's files add up to more than {limits.max_bytes:,} bytes."
            )
        per_point = record.point_bytes if name.endswith(".bin") else LABEL_BYTES
        if member.size > limits.max_points * per_point:
            raise ArchiveTooLarge(
                f"Archive member {name!r} holds more than {limits.max_points:,} points."
            )
        members.append(_Member(name, member.size, False, member.handle))
    return members


def _extract(
    members: list[_Member], dest: Path, record: PointRecord, layout: SequenceLayout, opener
) -> ExtractedDataset:
    """Read, check and write each file member into `layout`; then check scans and labels match
    up."""
    scans: dict[str, dict[str, int]] = {}
    labels: dict[str, dict[str, int]] = {}
    dest.mkdir(parents=True, exist_ok=True)
    root = dest.resolve()
    for member in members:
        seq, folder, stem, _ = _FILE.match(member.name).groups()
        stream = opener(member)
        if stream is None:
            raise ArchiveError(f"Archive member {member.name!r} cannot be read.")
        with stream:
            data = _read_limited(stream, member.size, member.name)
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
