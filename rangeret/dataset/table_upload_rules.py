"""What an uploaded archive of a version's tables may hold (nuScenes), and the checks of its tree.

    <version>/<table>.json                       the tables of one version (v1.0-mini, say)
    samples/LIDAR_TOP/<name>.pcd.bin             keyframe sweeps, in the profile's point record
    lidarseg/<version>/<token>_lidarseg.bin      optional labels, one uint8 per point
    panoptic/<version>/<token>_panoptic.npz      optional panoptic labels (nuScenes-panoptic)

and the folders of these (the sensor channel is the layout's). `TableLayout.upload_rules` gives
these rules, and whoever takes the upload lists, bounds and extracts the members with them as it
does a folder layout's (`rangeret.dataset.upload_rules`); once they are written, the version's
tables must read, name the profile's categories and list every sweep of the archive as a keyframe
(and every label or panoptic file as its labels, of one label per point), and every keyframe of
the tables must be in the archive. A scene has labels for all its keyframes or none.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Protocol

from rangeret.dataset.layout import (
    DatasetLayout,
    DatasetLayoutError,
    Discovery,
    ScanEntry,
    discover,
)
from rangeret.dataset.upload_rules import ArchiveError, ExtractedDataset
from rangeret.io.panoptic_labels import read_panoptic_npz
from rangeret.io.scans import PointRecord, ScanFormatError, parse_scan

#: A version folder's name (v1.0-mini, v1.0-trainval, v1.0-test).
_VERSION = r"v[0-9][A-Za-z0-9._-]{0,62}"
_TABLE = re.compile(rf"^({_VERSION})/([a-z_]{{1,64}})\.json$")
_LABEL = re.compile(rf"^lidarseg/({_VERSION})/[A-Za-z0-9]{{1,64}}_lidarseg\.bin$")
_PANOPTIC = re.compile(rf"^panoptic/({_VERSION})/[A-Za-z0-9]{{1,64}}_panoptic\.npz$")
#: Most problems of a tree named in one answer.
_SHOWN = 3


def _sweep_pattern(channel: str) -> re.Pattern[str]:
    return re.compile(rf"^samples/{re.escape(channel)}/[A-Za-z0-9_+-]{{1,200}}\.pcd\.bin$")


def _folder_pattern(channel: str) -> re.Pattern[str]:
    return re.compile(
        rf"^(({_VERSION})|samples(/{re.escape(channel)})?|(lidarseg|panoptic)(/({_VERSION}))?)/?$"
    )


class ChannelLayout(DatasetLayout, Protocol):
    """A layout of a version's tables, whose sweeps are those of one sensor channel."""

    @property
    def channel(self) -> str:
        """The sensor channel whose sweeps the archive holds (LIDAR_TOP)."""
        ...


class NuScenesRules:
    """The archive of a tables layout (`layout`), its sweeps in `record` (see the module)."""

    def __init__(self, record: PointRecord, layout: ChannelLayout) -> None:
        self.record = record
        self.layout = layout
        self._sweep = _sweep_pattern(layout.channel)
        self._folder = _folder_pattern(layout.channel)
        self.version: str | None = None
        self.tables: set[str] = set()
        self.sweeps: dict[str, int] = {}
        self.labels: dict[str, int] = {}
        self.panoptic: dict[str, int] = {}

    def check_name(self, name: str, is_dir: bool) -> None:
        """`ArchiveError` for a member outside the layout, or of a second version."""
        if is_dir:
            match = self._folder.match(name)
            if not match:
                raise ArchiveError(
                    f"Archive member {name[:200]!r} is a folder outside the nuScenes layout "
                    f"(a version folder, samples/{self.layout.channel}, lidarseg/<version>, "
                    "panoptic/<version>)."
                )
            self._version(match.group(2) or match.group(6))
            return
        match = _TABLE.match(name) or _LABEL.match(name) or _PANOPTIC.match(name)
        if match:
            self._version(match.group(1))
        elif not self._sweep.match(name):
            raise ArchiveError(
                f"Archive member {name[:200]!r} is not a table (<version>/*.json), a sweep "
                f"(samples/{self.layout.channel}/*.pcd.bin), a label file "
                "(lidarseg/<version>/*_lidarseg.bin) or a panoptic file "
                "(panoptic/<version>/*_panoptic.npz)."
            )

    def _version(self, version: str | None) -> None:
        """Note the archive's version; `ArchiveError` for a second one."""
        if version is None or version == self.version:
            return
        if self.version is not None:
            raise ArchiveError(
                f"The archive holds the versions {self.version} and {version}; upload one "
                "version's tables and files."
            )
        self.version = version

    def point_bytes(self, name: str) -> int | None:
        """A sweep's record size, a label's byte; None for a table or a panoptic file (its
        reader bounds what it declares)."""
        if name.endswith(".json") or _PANOPTIC.match(name):
            return None
        return self.layout.label_file.bytes if _LABEL.match(name) else self.record.point_bytes

    def accept(self, name: str, data: bytes, root: Path) -> Path:
        """Count a sweep's points or a label file's labels, note a table; the member's own path
        under `root` (its parts are checked already)."""
        if name.endswith(".json"):
            self.tables.add(name)
        elif _LABEL.match(name):
            width = self.layout.label_file.bytes
            if len(data) % width:
                raise ArchiveError(
                    f"Archive member {name!r} is {len(data)} bytes, not a whole number of "
                    f"uint{8 * width} labels."
                )
            self.labels[name] = len(data) // width
        elif _PANOPTIC.match(name):
            try:
                self.panoptic[name] = len(read_panoptic_npz(name, None, data))
            except ScanFormatError as exc:
                raise ArchiveError(f"Archive member {exc.source}: {exc.problem}.") from exc
        else:
            try:
                self.sweeps[name] = len(parse_scan(data, name, record=self.record))
            except ScanFormatError as exc:
                raise ArchiveError(f"Archive member {exc.source}: {exc.problem}.") from exc
        return root / name

    def finish(self, root: Path) -> ExtractedDataset:
        """The scenes of the version's tables, once the tables read and agree with the files."""
        version = self.version
        if version is None or f"{version}/scene.json" not in self.tables:
            raise ArchiveError(
                "The archive holds no nuScenes tables: put the version's tables in its folder, "
                "such as v1.0-mini/scene.json."
            )
        if not self.sweeps:
            raise ArchiveError(f"The archive holds no sweep under samples/{self.layout.channel}/.")
        try:
            scenes = self.layout.list_sequences(root, version=version)
            found = discover(root, scenes, layout=self.layout, version=version)
            panoptic = (
                discover(root, scenes, layout=self.layout, version=version, panoptic=True)
                if self.panoptic
                else None
            )
        except (DatasetLayoutError, ValueError) as exc:
            raise ArchiveError(
                f"The archive's tables cannot be read: {_relative(exc, root)}."
            ) from exc
        problems = [_relative(p, root) for p in found.problems]
        problems += self._unmatched(found, root)
        if panoptic is not None:
            problems += _unmatched_files(panoptic, root, self.panoptic, self.sweeps, "panoptic")
        if problems:
            more = f" (and {len(problems) - _SHOWN} more)" if len(problems) > _SHOWN else ""
            raise ArchiveError(
                f"The archive's tables and files do not agree: {'; '.join(problems[:_SHOWN])}"
                f"{more}."
            )
        return ExtractedDataset(
            root=root,
            sequences=scenes,
            scans=len(found.scans),
            labelled=[s for s, frames in found.by_sequence().items() if not _unlabelled(frames)],
            version=version,
        )

    def _unmatched(self, found: Discovery, root: Path) -> list[str]:
        """Sweeps and label files that no keyframe has, label files of another length than their
        sweep, and scenes labelled in part."""
        problems = []
        scans = found.scans
        keyframes = {_name(e.scan_path, root): e for e in scans}
        labels = {_name(e.label_path, root): e for e in scans if e.label_path is not None}
        for name in sorted(self.sweeps.keys() - keyframes.keys()):
            problems.append(
                f"{name} is not the sweep of a keyframe in {self.version}/sample_data.json"
            )
        for name in sorted(self.labels.keys() - labels.keys()):
            problems.append(
                f"{name} is not the label file of a keyframe in {self.version}/lidarseg.json"
            )
        for name, entry in sorted(labels.items()):
            sweep = _name(entry.scan_path, root)
            if self.labels[name] != self.sweeps[sweep]:
                problems.append(
                    f"{name} holds {self.labels[name]} labels but its sweep {sweep} has "
                    f"{self.sweeps[sweep]} points"
                )
        for scene, entries in found.by_sequence().items():
            missing = _unlabelled(entries)
            if 0 < len(missing) < len(entries):
                problems.append(
                    f"scene {scene} has label files for some keyframes but not for "
                    f"{len(missing)} of them (the first: sample_data {missing[0].name})"
                )
        return problems


def _unmatched_files(
    found: Discovery, root: Path, files: dict[str, int], sweeps: dict[str, int], table: str
) -> list[str]:
    """Label files of `table` (with their label counts) that no keyframe of its table has, and
    those of another length than their sweep."""
    named = {_name(e.label_path, root): e for e in found.scans if e.label_path is not None}
    problems = [
        f"{name} is not the {table} file of a keyframe in its version's {table}.json"
        for name in sorted(files.keys() - named.keys())
    ]
    for name, entry in sorted(named.items()):
        sweep = _name(entry.scan_path, root)
        if name in files and sweep in sweeps and files[name] != sweeps[sweep]:
            problems.append(
                f"{name} holds {files[name]} labels but its sweep {sweep} has {sweeps[sweep]} "
                "points"
            )
    return problems


def _unlabelled(keyframes: list[ScanEntry]) -> list[ScanEntry]:
    """The keyframes without a label file."""
    return [e for e in keyframes if e.label_path is None]


def _name(path: Path, root: Path) -> str:
    """A file's path in the archive."""
    return path.relative_to(root).as_posix()


def _relative(problem: object, root: Path) -> str:
    """A problem's text with the extraction folder left out, and no closing full stop."""
    return str(problem).replace(f"{root}/", "").replace(str(root), "the archive").rstrip(".")
