"""Safe extraction of uploaded sequence archives (.zip, .tar, .tar.gz) into a job's folder.

Every entry counts against `max_members`, folders included, and is counted as the archive is
listed, before its listing is held in memory (`service.archives.listing`). The files' declared
sizes may add up to at most `max_extracted_bytes`, checked before anything is written and again
on the bytes actually read; there is no compression-ratio rule, since a label file of one class
compresses like a bomb of zeros. `max_bytes` bounds the archive file itself.

Every member is checked before anything is written: no absolute path, no `..`, no link, device,
pipe or sparse file, and nothing but what the `ArchiveRules` the layout gives take
(`DatasetLayout.upload_rules`, in the library: `sequences/XX/velodyne/NNNNNN.bin` and
`sequences/XX/labels/NNNNNN.label` for every folder layout in `rangeret.dataset.upload_rules`,
nuScenes' tables and sweeps in `rangeret.dataset.table_upload_rules`). Then each file is read
(never more than its declared size), checked by the rules (a scan of the profile's point record,
a label file) and written under the destination where the rules put it, with names built from
the checked parts only; the rules then check that the files make one dataset.
"""

from __future__ import annotations

import gzip
import re
import stat
import tarfile
import zipfile
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from rangeret.dataset.layout import SequenceLayout
from rangeret.dataset.upload_rules import (
    ArchiveError,
    ArchiveRules,
    ArchiveTooLarge,
    ExtractedDataset,
)
from rangeret.io.scans import PointRecord
from service.archives.listing import (
    MAX_NAME,
    CheckedTarFile,
    TarHeaders,
    archive_kind,
    count_zip_entries,
    sparse_member,
    too_many_members,
)


@dataclass(frozen=True)
class ArchiveLimits:
    """Limits on what one archive may hold: its own size, its entries (folders included), each
    file's points and its files' total size once extracted."""

    max_bytes: int
    max_members: int
    max_points: int
    max_extracted_bytes: int


@dataclass(frozen=True)
class _Member:
    name: str
    size: int
    is_dir: bool
    handle: object


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


def _check_name(raw: str, is_dir: bool, rules: ArchiveRules) -> str:
    """The member's checked name, or ArchiveError saying why it is refused."""
    if len(raw) > MAX_NAME:
        raise ArchiveError(
            f"Archive member {raw[:200]!r}... has a name of {len(raw):,} characters, longer than "
            f"the {MAX_NAME:,} allowed."
        )
    problem = _escape_problem(raw)
    if problem:
        raise ArchiveError(
            f"Archive member {raw[:200]!r} {problem} and would escape the job folder."
        )
    name = _clean(raw)
    if not (is_dir and name in ("", ".")):
        rules.check_name(name, is_dir)
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
            raise ArchiveError(sparse_member(info.name))
        if not (info.isfile() or info.isdir()):
            raise ArchiveError(f"Archive member {info.name[:200]!r} is not a plain file or folder.")
        yield _Member(info.name, info.size, info.isdir(), info)


def extract_archive(
    archive: Path,
    dest: Path,
    limits: ArchiveLimits,
    *,
    record: PointRecord,
    layout: SequenceLayout,
) -> ExtractedDataset:
    """Check every member of `archive` (scans as `record`s), then write its scans and labels
    under `dest` in `layout`, so the dataset there reads like any other of its profile."""
    return extract_with(archive, dest, limits, layout.upload_rules(record))


def extract_with(
    archive: Path, dest: Path, limits: ArchiveLimits, rules: ArchiveRules
) -> ExtractedDataset:
    """Check every member of `archive` against the limits and `rules`, then write its files under
    `dest` where the rules put them; the dataset they make."""
    size = archive.stat().st_size
    if size > limits.max_bytes:
        raise ArchiveTooLarge(
            f"The archive is {size:,} bytes, more than the limit of {limits.max_bytes:,}."
        )
    kind = archive_kind(archive)
    try:
        if kind == "zip":
            entries = count_zip_entries(archive, limits.max_members)
            with zipfile.ZipFile(archive) as zf:
                if len(zf.filelist) != entries:
                    raise ArchiveError(
                        f"The zip archive lists {len(zf.filelist):,} entries where its central "
                        f"directory holds {entries:,}; the archive is damaged."
                    )
                members = _listing(_zip_members(zf), limits, rules)
                return _extract(members, dest, limits, rules, lambda m: zf.open(m.handle))
        headers = TarHeaders(max_count=limits.max_members)
        mode = "r:gz" if kind == "tar.gz" else "r:"
        with CheckedTarFile.open(archive, mode, extended_headers=headers) as tf:
            members = _listing(_tar_members(tf), limits, rules)
            return _extract(members, dest, limits, rules, lambda m: tf.extractfile(m.handle))
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


def _listing(found: Iterator[_Member], limits: ArchiveLimits, rules: ArchiveRules) -> list[_Member]:
    """Every member, checked for names, kinds, duplicates and the limits as it is listed (each
    entry counted, folders too, and the files' declared sizes added up), before any write."""
    members: list[_Member] = []
    names: set[str] = set()
    total = 0
    for seen, member in enumerate(found, start=1):
        if seen > limits.max_members:
            raise ArchiveTooLarge(too_many_members(limits.max_members))
        name = _check_name(member.name, member.is_dir, rules)
        if member.is_dir:
            continue
        if name in names:
            raise ArchiveError(f"Archive member {name!r} appears more than once.")
        names.add(name)
        total += member.size
        if total > limits.max_extracted_bytes:
            raise ArchiveTooLarge(_too_big(limits.max_extracted_bytes))
        per_point = rules.point_bytes(name)
        if per_point is not None and member.size > limits.max_points * per_point:
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
    rules: ArchiveRules,
    opener: Callable[[_Member], IO[bytes] | None],
) -> ExtractedDataset:
    """Read, check and write each file member where `rules` put it, counting the bytes actually
    read against the extracted limit; then let the rules check the files make one dataset."""
    dest.mkdir(parents=True, exist_ok=True)
    root = dest.resolve()
    extracted = 0
    for member in members:
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
        target = rules.accept(member.name, data, root)
        if not target.resolve().is_relative_to(root):
            raise ArchiveError(f"Archive member {member.name!r} would escape the job folder.")
        target.parent.mkdir(parents=True, exist_ok=True)
        with open(target, "xb") as out:
            out.write(data)
    return rules.finish(root)
