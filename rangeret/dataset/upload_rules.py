"""What an uploaded dataset archive may hold: the rules a layout gives, and those of folders.

An archive's members are listed, bounded and extracted by whoever takes the upload (the gateway);
the layout decides which members it may hold, where each file goes and when the files make one
dataset (`DatasetLayout.upload_rules`). For every folder layout (`FolderRules`):

    sequences/XX/velodyne/NNNNNN.bin      scans, in the profile's point record
    sequences/XX/labels/NNNNNN.label      optional labels, one uint32 per point

and the folders of these, written into the layout's sequence folders; a sequence has labels for
all its scans or none. A version's tables have their own (`rangeret.dataset.table_upload_rules`).
Every refusal is an `ArchiveError` of one sentence, 413 (`ArchiveTooLarge`) for a limit.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

from rangeret.io.scans import LABEL_BYTES, PointRecord, ScanFormatError, parse_scan

_DIRECTORY = re.compile(r"^sequences(/[A-Za-z0-9_-]{1,64}(/(velodyne|labels))?)?/?$")
_FILE = re.compile(
    r"^sequences/([A-Za-z0-9_-]{1,64})/(velodyne|labels)/([A-Za-z0-9_-]{1,64})\.(bin|label)$"
)
_SUFFIX = {"velodyne": "bin", "labels": "label"}


class ArchiveError(ValueError):
    """An upload that is not a safe archive in the expected layout."""


class ArchiveTooLarge(ArchiveError):
    """An archive over the member-count, size, extracted-size or points limits."""


@dataclass
class ExtractedDataset:
    """The dataset an archive held: where it now lies and what it contains (and, for a tables
    layout, the version of its tables)."""

    root: Path
    sequences: list[str]
    scans: int
    labelled: list[str] = field(default_factory=list)
    version: str | None = None


class ArchiveRules(Protocol):
    """What the archive of one dataset layout may hold, and how its files become a dataset.

    One instance checks one archive: `accept` notes what each file holds for `finish`.
    """

    def check_name(self, name: str, is_dir: bool) -> None:
        """`ArchiveError` when a member (its name safe and without a leading `./`) is not one
        the layout holds."""
        ...

    def point_bytes(self, name: str) -> int | None:
        """Bytes per point of a file member, for the points limit (None: not a point file)."""
        ...

    def accept(self, name: str, data: bytes, root: Path) -> Path:
        """Check a file member's bytes (`ArchiveError` when they are wrong) and return where it
        goes under the destination `root`."""
        ...

    def finish(self, root: Path) -> ExtractedDataset:
        """The dataset extracted under `root`; `ArchiveError` when its files do not make one."""
        ...


class SequenceFolders(Protocol):
    """What the folder rules ask of a folder layout: where its sequence folders sit."""

    def sequences_root(self, root: Path | str) -> Path:
        """The folder that holds the sequence folders under `root`."""
        ...


class FolderRules:
    """A folder layout's archive: `sequences/XX/velodyne/*.bin` scans of `record` and optional
    `sequences/XX/labels/*.label`, written into `layout`'s folders."""

    def __init__(self, record: PointRecord, layout: SequenceFolders) -> None:
        self.record = record
        self.layout = layout
        self.scans: dict[str, dict[str, int]] = {}
        self.labels: dict[str, dict[str, int]] = {}

    def check_name(self, name: str, is_dir: bool) -> None:
        """`ArchiveError` for a member outside `sequences/XX/velodyne|labels`."""
        if is_dir:
            if not _DIRECTORY.match(name):
                raise ArchiveError(
                    f"Archive member {name[:200]!r} is a folder outside the layout "
                    "sequences/XX/velodyne|labels."
                )
            return
        match = _FILE.match(name)
        if not match or _SUFFIX[match.group(2)] != match.group(4):
            raise ArchiveError(
                f"Archive member {name[:200]!r} is not a sequences/XX/velodyne/*.bin scan or "
                "sequences/XX/labels/*.label file."
            )

    def point_bytes(self, name: str) -> int:
        """A scan's record size, or a label's four bytes."""
        return self.record.point_bytes if name.endswith(".bin") else LABEL_BYTES

    def accept(self, name: str, data: bytes, root: Path) -> Path:
        """Count a scan's points or a label file's labels; its place in the layout under
        `root`."""
        seq, folder, stem, _ = _FILE.match(name).groups()
        if folder == "velodyne":
            try:
                points = parse_scan(data, name, record=self.record)
            except ScanFormatError as exc:
                raise ArchiveError(f"Archive member {exc.source}: {exc.problem}.") from exc
            self.scans.setdefault(seq, {})[stem] = len(points)
        else:
            if len(data) % LABEL_BYTES:
                raise ArchiveError(
                    f"Archive member {name!r} is {len(data)} bytes, not a whole number of "
                    "uint32 labels."
                )
            self.labels.setdefault(seq, {})[stem] = len(data) // LABEL_BYTES
        return self.layout.sequences_root(root) / seq / folder / f"{stem}.{_SUFFIX[folder]}"

    def finish(self, root: Path) -> ExtractedDataset:
        """The extracted dataset, once every label file is known to match a scan of its
        length."""
        return _summarise(root, self.scans, self.labels)


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
