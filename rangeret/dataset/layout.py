"""Dataset folder layouts: finding sequences, scans, labels and predictions.

    ROOT/sequences/XX/velodyne/NNNNNN.bin      scans (SemanticKITTI; `SequenceLayout` says where
    ROOT/sequences/XX/labels/NNNNNN.label      sequence folders sit for other datasets)
    PRED/sequences/XX/predictions/NNNNNN.label predictions, for every dataset

Scans are listed in sorted order and matched to labels by file stem; anything unmatched is
reported by name rather than silently skipped.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from rangeret.dataset.labels import LabelConfig
from rangeret.exceptions import DatasetError
from rangeret.io.scans import (
    LABEL_BYTES,
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

    def to_dict(self) -> dict:
        """Plain-data form."""
        return {"sequence_folders": list(self.sequence_folders), "id_digits": self.id_digits}


#: SemanticKITTI's layout: ROOT/sequences/XX.
KITTI_LAYOUT = SequenceLayout()


@dataclass(frozen=True)
class ScanEntry:
    """One scan of a dataset: its sequence, its file stem and where its files are."""

    sequence: str
    name: str
    scan_path: Path
    label_path: Path | None

    @property
    def key(self) -> str:
        """`"XX/NNNNNN"`, the scan's name in messages and reports."""
        return f"{self.sequence}/{self.name}"


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
    """Folder of a sequence's predictions in a predictions tree."""
    return Path(root) / "sequences" / sequence / "predictions"


def prediction_path(pred_root: Path | str, sequence: str, name: str) -> Path:
    """Where the prediction of scan `sequence/name` lives in a predictions tree."""
    return predictions_dir(pred_root, sequence) / f"{name}.label"


def confidence_path(pred_root: Path | str, sequence: str, name: str) -> Path:
    """Where the point confidences of scan `sequence/name` live in a predictions tree, beside
    its prediction (`sequences/XX/confidence/NNNNNN.npy`)."""
    return Path(pred_root) / "sequences" / sequence / "confidence" / f"{name}.npy"


def list_sequences(root: Path | str, *, layout: SequenceLayout) -> list[str]:
    """Sorted names of the sequence folders of a dataset (those holding a velodyne folder)."""
    base = layout.sequences_root(root)
    if not base.is_dir():
        raise DatasetLayoutError(f"{base} does not exist: expected its sequence folders there")
    return sorted(p.name for p in base.iterdir() if (p / "velodyne").is_dir())


def normalise_sequence(name: str | int, *, layout: SequenceLayout) -> str:
    """The on-disk form of a sequence id (8 -> "08" for SemanticKITTI, "008" for 3-digit ids)."""
    return layout.normalise(name)


def resolve_sequences(
    split: str | None = None,
    sequences: Iterable[str | int] | None = None,
    *,
    labels: LabelConfig,
    layout: SequenceLayout,
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
    root: Path | str, sequences: Sequence[str], *, layout: SequenceLayout
) -> list[str]:
    """Those of `sequences` that `root` does not hold (no velodyne folder), in their order."""
    return [s for s in sequences if not velodyne_dir(root, s, layout=layout).is_dir()]


def _stems(folder: Path, suffix: str) -> dict[str, Path]:
    if not folder.is_dir():
        return {}
    with os.scandir(folder) as it:
        return {
            e.name[: -len(suffix)]: Path(e.path)
            for e in it
            if e.name.endswith(suffix) and not e.name.startswith(".")
        }


def discover(
    root: Path | str,
    sequences: Sequence[str],
    with_labels: bool = False,
    missing_ok: bool = False,
    *,
    layout: SequenceLayout,
) -> Discovery:
    """List the scans of `sequences` under `root`, sorted, matched to their labels by name.

    Label files found are always attached; with `with_labels` they are required, and a scan
    without a label file and a label file without a scan are problems. A missing or empty
    sequence folder is a problem unless `missing_ok` (partial copies).
    """
    root = Path(root)
    result = Discovery(root=root, sequences=[])
    for seq in sequences:
        vdir = velodyne_dir(root, seq, layout=layout)
        if not vdir.is_dir():
            if not missing_ok:
                result.problems.append(f"{vdir} does not exist (sequence {seq} is missing)")
            continue
        result.sequences.append(seq)
        scans = _stems(vdir, ".bin")
        if not scans and not missing_ok:
            result.problems.append(f"{vdir} holds no .bin scan")
        ldir = labels_dir(root, seq, layout=layout)
        labels = _stems(ldir, ".label")
        if with_labels:
            for stem in sorted(scans.keys() - labels.keys()):
                result.problems.append(
                    f"{ldir / (stem + '.label')} is missing (scan {seq}/{stem} has no ground truth)"
                )
            for stem in sorted(labels.keys() - scans.keys()):
                result.problems.append(
                    f"{labels[stem]} has no matching scan {vdir / (stem + '.bin')}"
                )
        for stem in sorted(scans):
            result.scans.append(ScanEntry(seq, stem, scans[stem], labels.get(stem)))
    return result


def is_complete(
    entry: ScanEntry,
    out: Path,
    *,
    record: PointRecord,
    with_confidence: bool = False,
) -> bool:
    """Whether the scan's prediction exists with one label per point (a finished earlier run),
    and its confidence file too when `with_confidence`."""
    pred = prediction_path(out, entry.sequence, entry.name)
    try:
        whole = pred.stat().st_size == scan_num_points(entry.scan_path, record=record) * LABEL_BYTES
    except (OSError, ScanFormatError):
        return False
    return whole and (
        not with_confidence or confidence_path(out, entry.sequence, entry.name).is_file()
    )


def list_scans(
    dataset: Path | str,
    sequences: Sequence[str],
    missing_ok: bool = False,
    *,
    layout: SequenceLayout,
) -> list[ScanEntry]:
    """The scans of `sequences`, in order; a missing or empty sequence is an error naming it
    unless `missing_ok` (a partial local copy, logged)."""
    found = discover(dataset, sequences, missing_ok=missing_ok, layout=layout)
    if found.problems:
        raise DatasetLayoutError("; ".join(found.problems))
    absent = sorted(set(sequences) - set(found.sequences))
    if absent:
        log.warning("sequences %s are not in %s: predicting the others", ", ".join(absent), dataset)
    return found.scans
