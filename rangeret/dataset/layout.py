"""Dataset layouts: finding sequences, scans, labels and where each scan's prediction goes.

A layout turns a dataset ROOT and the sequences chosen into `ScanEntry`s, each knowing its scan,
its label file and the relative path of its prediction in a predictions tree. Two kinds exist:
folders (`SequenceLayout`, below) and a version's tables (nuScenes,
`rangeret.dataset.table_layout`); both answer the `DatasetLayout` protocol.

    ROOT/sequences/XX/velodyne/NNNNNN.bin      scans (SemanticKITTI; `SequenceLayout` says where
    ROOT/sequences/XX/labels/NNNNNN.label      sequence folders sit for other datasets)
    PRED/sequences/XX/predictions/NNNNNN.label predictions, for every folder layout

Scans are listed in sorted order and matched to labels by file stem; anything unmatched is
reported by name rather than silently skipped.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from rangeret.dataset.labels import LabelConfig
from rangeret.dataset.upload_rules import ArchiveRules, FolderRules
from rangeret.exceptions import DatasetError
from rangeret.io.panoptic_labels import SHIFTED, NpzLabelFile, PanopticEncoding
from rangeret.io.scans import (
    KITTI_LABELS,
    LabelFile,
    PointRecord,
    ScanFormatError,
    scan_num_points,
)

log = logging.getLogger(__name__)


class DatasetLayoutError(DatasetError, ValueError):
    """A dataset or predictions tree that does not have the expected layout or is missing files."""


@dataclass(frozen=True)
class SequenceLayout:
    """Where a dataset's sequence folders sit under its ROOT, and how their ids are written.

    `sequence_folders` are tried in order and the first that exists holds the sequences ("." is
    ROOT itself); `id_digits` pads numeric ids (8 -> "08" with 2 digits, "008" with 3).
    """

    sequence_folders: tuple[str, ...] = ("sequences",)
    id_digits: int = 2

    def __post_init__(self) -> None:
        if not self.sequence_folders:
            raise DatasetLayoutError("a layout needs at least one sequence folder")
        if not 1 <= self.id_digits <= 8:
            raise DatasetLayoutError(f"id_digits must be 1 to 8, got {self.id_digits}")

    def sequences_root(self, root: Path | str) -> Path:
        """The folder that holds the sequence folders: the first candidate that exists."""
        root = Path(root)
        for folder in self.sequence_folders:
            candidate = root if folder in ("", ".") else root / folder
            if candidate.is_dir():
                return candidate
        first = self.sequence_folders[0]
        return root if first in ("", ".") else root / first

    def normalise(self, name: str | int) -> str:
        """The id as written on disk: numeric ids padded to `id_digits`, others kept as given."""
        text = str(name).strip()
        return f"{int(text):0{self.id_digits}d}" if text.isdigit() else text

    @property
    def label_file(self) -> LabelFile:
        """SemanticKITTI's `.label` files: one uint32 per point."""
        return KITTI_LABELS

    @property
    def panoptic_encoding(self) -> PanopticEncoding:
        """SemanticKITTI panoptic labels (`instance << 16 | raw id`), in the same `.label`
        files at the same places as the semantic ones."""
        return SHIFTED

    @property
    def panoptic_file(self) -> LabelFile:
        """Its panoptic label files: `.label` files of uint32, as the semantic ones."""
        return KITTI_LABELS

    @property
    def folders(self) -> SequenceLayout:
        """The layout as folders of sequences: itself."""
        return self

    def versions(self, root: Path | str) -> list[str] | None:
        """None: folders of sequences have no versions."""
        return None

    def check_version(self, version: str | None) -> None:
        """A `DatasetLayoutError` when a version is given: folders have none."""
        _no_version(version)

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form."""
        return {"sequence_folders": list(self.sequence_folders), "id_digits": self.id_digits}

    def upload_rules(self, record: PointRecord) -> ArchiveRules:
        """An upload's rules: `sequences/XX/velodyne|labels` files, written into these folders."""
        return FolderRules(record, self)

    def list_sequences(self, root: Path | str, *, version: str | None = None) -> list[str]:
        """Sorted names of the sequence folders (those holding a velodyne folder)."""
        _no_version(version)
        base = self.sequences_root(root)
        if not base.is_dir():
            raise DatasetLayoutError(f"{base} does not exist: expected its sequence folders there")
        return sorted(p.name for p in base.iterdir() if (p / "velodyne").is_dir())

    def missing(
        self, root: Path | str, sequences: Sequence[str], *, version: str | None = None
    ) -> list[str]:
        """Those of `sequences` without a velodyne folder under `root`, in their order."""
        _no_version(version)
        return [s for s in sequences if not velodyne_dir(root, s, layout=self).is_dir()]

    def discover(
        self,
        root: Path | str,
        sequences: Sequence[str],
        with_labels: bool = False,
        missing_ok: bool = False,
        *,
        version: str | None = None,
        split: str | None = None,
        panoptic: bool = False,
    ) -> Discovery:
        """The scans of `sequences` under `root`, sorted, matched to their labels by file stem
        (`split` does not change where a folder layout's predictions go, nor `panoptic` where
        they go or which label files hold the ground truth: a `.label` holds both)."""
        _no_version(version)
        root = Path(root)
        result = Discovery(root=root, sequences=[])
        missing = [s for s in sequences if not velodyne_dir(root, s, layout=self).is_dir()]
        if missing and not missing_ok:
            result.problems.append(_missing_problem(root, missing, self))
        for seq in sequences:
            vdir = velodyne_dir(root, seq, layout=self)
            if seq in missing:
                continue
            result.sequences.append(seq)
            scans = _stems(vdir, ".bin")
            if not scans and not missing_ok:
                result.problems.append(f"{vdir} holds no .bin scan")
            ldir = labels_dir(root, seq, layout=self)
            labels = _stems(ldir, ".label")
            if with_labels:
                for stem in sorted(scans.keys() - labels.keys()):
                    result.problems.append(
                        f"{ldir / (stem + '.label')} is missing "
                        f"(scan {seq}/{stem} has no ground truth)"
                    )
                for stem in sorted(labels.keys() - scans.keys()):
                    result.problems.append(
                        f"{labels[stem]} has no matching scan {vdir / (stem + '.bin')}"
                    )
            for stem in sorted(scans):
                result.scans.append(
                    ScanEntry(
                        seq,
                        stem,
                        scans[stem],
                        labels.get(stem),
                        f"sequences/{seq}/predictions/{stem}.label",
                        f"sequences/{seq}/confidence/{stem}.npy",
                    )
                )
        return result


#: SemanticKITTI's layout: ROOT/sequences/XX.
KITTI_LAYOUT = SequenceLayout()


@dataclass(frozen=True)
class ScanEntry:
    """One scan of a dataset: its sequence, its name, where its files are, and where its
    prediction and confidence go in a predictions tree (paths relative to the tree's root)."""

    sequence: str
    name: str
    scan_path: Path
    label_path: Path | None
    prediction: str
    confidence: str
    #: How its label file and its prediction hold one label per point.
    label_file: LabelFile | NpzLabelFile = KITTI_LABELS

    @property
    def key(self) -> str:
        """`"XX/NNNNNN"`, the scan's name in messages and reports."""
        return f"{self.sequence}/{self.name}"

    def prediction_in(self, root: Path | str) -> Path:
        """Where its prediction lives in the predictions tree `root`."""
        return Path(root) / self.prediction

    def confidence_in(self, root: Path | str) -> Path:
        """Where its point confidences live in the predictions tree `root`."""
        return Path(root) / self.confidence


@dataclass
class Discovery:
    """The scans found under a dataset root, and every file problem found on the way."""

    root: Path
    sequences: list[str]
    scans: list[ScanEntry] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)

    def by_sequence(self) -> dict[str, list[ScanEntry]]:
        """Scans grouped by sequence, in sequence order."""
        groups: dict[str, list[ScanEntry]] = {s: [] for s in self.sequences}
        for entry in self.scans:
            groups[entry.sequence].append(entry)
        return groups


class DatasetLayout(Protocol):
    """What every layout answers: the sequences a ROOT holds and the scans of those chosen, and
    what it allows (versions, resampling, simulation, uploads)."""

    @property
    def label_file(self) -> LabelFile:
        """How its label and prediction files hold one label per point."""
        ...

    @property
    def panoptic_encoding(self) -> PanopticEncoding:
        """How its panoptic labels pack a point's semantic label and its object."""
        ...

    @property
    def panoptic_file(self) -> LabelFile | NpzLabelFile:
        """How its panoptic label and prediction files hold one label per point."""
        ...

    @property
    def folders(self) -> SequenceLayout | None:
        """The layout as folders of sequences, or None where it is not (a version's tables):
        what `adapt` resamples and another sensor's data is read in."""
        ...

    def versions(self, root: Path | str) -> list[str] | None:
        """The version folders ROOT holds, or None for a layout without versions."""
        ...

    def check_version(self, version: str | None) -> None:
        """A `DatasetLayoutError` when `version` is given to a layout without versions."""
        ...

    def normalise(self, name: str | int) -> str:
        """A sequence id as the layout writes it."""
        ...

    def to_dict(self) -> dict[str, Any]:
        """The profile's `layout` section."""
        ...

    def upload_rules(self, record: PointRecord) -> ArchiveRules:
        """What an uploaded archive (scans of `record`) may hold; callers need not know layouts."""
        ...

    def discover(
        self,
        root: Path | str,
        sequences: Sequence[str],
        with_labels: bool = False,
        missing_ok: bool = False,
        *,
        version: str | None = None,
        split: str | None = None,
        panoptic: bool = False,
    ) -> Discovery:
        """The scans of `sequences` under `root` and every problem found on the way; with
        `panoptic`, their panoptic ground truth and where their panoptic predictions go."""
        ...

    def missing(
        self, root: Path | str, sequences: Sequence[str], *, version: str | None = None
    ) -> list[str]:
        """Those of `sequences` that `root` does not hold, in their order."""
        ...

    def list_sequences(self, root: Path | str, *, version: str | None = None) -> list[str]:
        """Every sequence `root` holds, sorted."""
        ...


def sequence_dir(root: Path | str, sequence: str, *, layout: SequenceLayout) -> Path:
    """Folder of one sequence of a dataset."""
    return layout.sequences_root(root) / sequence


def velodyne_dir(root: Path | str, sequence: str, *, layout: SequenceLayout) -> Path:
    """Folder of a sequence's scans."""
    return sequence_dir(root, sequence, layout=layout) / "velodyne"


def labels_dir(root: Path | str, sequence: str, *, layout: SequenceLayout) -> Path:
    """Folder of a sequence's ground-truth labels."""
    return sequence_dir(root, sequence, layout=layout) / "labels"


def predictions_dir(root: Path | str, sequence: str) -> Path:
    """Folder of a sequence's predictions in a folder layout's predictions tree."""
    return Path(root) / "sequences" / sequence / "predictions"


def prediction_path(pred_root: Path | str, sequence: str, name: str) -> Path:
    """Where the prediction of scan `sequence/name` of a folder layout lives in a predictions
    tree."""
    return predictions_dir(pred_root, sequence) / f"{name}.label"


def list_sequences(
    root: Path | str, *, layout: DatasetLayout, version: str | None = None
) -> list[str]:
    """Sorted names of the sequences of a dataset (folders holding a velodyne folder, or the
    scenes of a version's tables)."""
    return layout.list_sequences(root, version=version)


def resolve_sequences(
    split: str | None = None,
    sequences: Iterable[str | int] | None = None,
    *,
    labels: LabelConfig,
    layout: DatasetLayout,
) -> list[str]:
    """The sequences a command works on: those named, or those of a split of the label config.

    Exactly one of `split` and `sequences` must be given; named sequences need not belong to
    any official split, so data outside the benchmark is served too.
    """
    if (split is None) == (sequences is None):
        raise DatasetLayoutError(
            "give either a split or a list of sequences, not both and not neither"
        )
    if sequences is not None:
        names = [layout.normalise(s) for s in sequences]
        if not names:
            raise DatasetLayoutError("the list of sequences is empty")
        return sorted(dict.fromkeys(names))
    return list(labels.split(split))


def missing_sequences(
    root: Path | str,
    sequences: Sequence[str],
    *,
    layout: DatasetLayout,
    version: str | None = None,
) -> list[str]:
    """Those of `sequences` that `root` does not hold, in their order."""
    return layout.missing(root, sequences, version=version)


def discover(
    root: Path | str,
    sequences: Sequence[str],
    with_labels: bool = False,
    missing_ok: bool = False,
    *,
    layout: DatasetLayout,
    version: str | None = None,
    split: str | None = None,
    panoptic: bool = False,
) -> Discovery:
    """List the scans of `sequences` under `root`, in order, matched to their labels.

    Label files found are always attached; with `with_labels` they are required, and a scan
    without a label file (and, in folders, a label file without a scan) is a problem. A missing
    or empty sequence is a problem unless `missing_ok` (partial copies). `version` chooses a
    tables layout's version; `split`, the folder its predictions go to; `panoptic`, the panoptic
    ground truth and predictions instead of the semantic ones.
    """
    return layout.discover(
        root, sequences, with_labels, missing_ok, version=version, split=split, panoptic=panoptic
    )


def is_complete(
    entry: ScanEntry,
    out: Path,
    *,
    record: PointRecord,
    with_confidence: bool = False,
) -> bool:
    """Whether the scan's prediction exists with one label per point (a finished earlier run),
    and its confidence file too when `with_confidence`."""
    pred = entry.prediction_in(out)
    try:
        points = scan_num_points(entry.scan_path, record=record)
    except (OSError, ScanFormatError):
        return False
    whole = entry.label_file.holds(pred, points)
    return whole and (not with_confidence or entry.confidence_in(out).is_file())


def list_scans(
    dataset: Path | str,
    sequences: Sequence[str],
    missing_ok: bool = False,
    *,
    layout: DatasetLayout,
    version: str | None = None,
    split: str | None = None,
    panoptic: bool = False,
) -> list[ScanEntry]:
    """The scans of `sequences`, in order; a missing or empty sequence is an error naming it
    unless `missing_ok` (a partial local copy, logged)."""
    found = discover(
        dataset,
        sequences,
        missing_ok=missing_ok,
        layout=layout,
        version=version,
        split=split,
        panoptic=panoptic,
    )
    if found.problems:
        raise DatasetLayoutError("; ".join(found.problems))
    absent = sorted(set(sequences) - set(found.sequences))
    if absent:
        log.warning("sequences %s are not in %s: predicting the others", ", ".join(absent), dataset)
    return found.scans


def _missing_problem(root: Path, missing: Sequence[str], layout: DatasetLayout) -> str:
    """One problem naming every missing sequence: its scan folder for one, the list for more."""
    first = velodyne_dir(root, missing[0], layout=layout)
    if len(missing) == 1:
        return f"{first} does not exist (sequence {missing[0]} is missing)"
    shown = first.relative_to(root).as_posix().replace(str(missing[0]), "<sequence>", 1)
    return (
        f"{len(missing)} sequences are missing under {root} (no {shown} folder): "
        f"{', '.join(missing)}"
    )


def _stems(folder: Path, suffix: str) -> dict[str, Path]:
    if not folder.is_dir():
        return {}
    with os.scandir(folder) as it:
        return {
            e.name[: -len(suffix)]: Path(e.path)
            for e in it
            if e.name.endswith(suffix) and not e.name.startswith(".")
        }


def _no_version(version: str | None) -> None:
    if version is not None:
        raise DatasetLayoutError(
            f"--version {version} is for a dataset of tables (nuScenes); this profile's dataset "
            "is folders of sequences"
        )
