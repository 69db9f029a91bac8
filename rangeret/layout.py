"""The SemanticKITTI folder layout: finding sequences, scans, labels and predictions.

    ROOT/sequences/XX/velodyne/NNNNNN.bin      scans
    ROOT/sequences/XX/labels/NNNNNN.label      ground truth (optional)
    PRED/sequences/XX/predictions/NNNNNN.label predictions

Scans are listed in sorted order and matched to labels by file stem; anything unmatched is
reported by name rather than silently skipped.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from rangeret.labels import LabelConfig, semantickitti


class DatasetLayoutError(ValueError):
    """A dataset or predictions tree that does not have the expected layout or is missing files."""


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


def velodyne_dir(root: Path | str, sequence: str) -> Path:
    """Folder of a sequence's scans."""
    return Path(root) / "sequences" / sequence / "velodyne"


def labels_dir(root: Path | str, sequence: str) -> Path:
    """Folder of a sequence's ground-truth labels."""
    return Path(root) / "sequences" / sequence / "labels"


def predictions_dir(root: Path | str, sequence: str) -> Path:
    """Folder of a sequence's predictions in a predictions tree."""
    return Path(root) / "sequences" / sequence / "predictions"


def prediction_path(pred_root: Path | str, sequence: str, name: str) -> Path:
    """Where the prediction of scan `sequence/name` lives in a predictions tree."""
    return predictions_dir(pred_root, sequence) / f"{name}.label"


def list_sequences(root: Path | str) -> list[str]:
    """Sorted names of the sequence folders under `ROOT/sequences`."""
    base = Path(root) / "sequences"
    if not base.is_dir():
        raise DatasetLayoutError(
            f"{base} does not exist: expected ROOT/sequences/XX/velodyne/*.bin"
        )
    return sorted(p.name for p in base.iterdir() if p.is_dir())


def normalise_sequence(name: str | int) -> str:
    """Two-digit form of a numeric sequence name (8 -> "08"); other names are kept as given."""
    text = str(name).strip()
    return f"{int(text):02d}" if text.isdigit() else text


def resolve_sequences(
    split: str | None = None,
    sequences: Iterable[str | int] | None = None,
    config: LabelConfig | None = None,
) -> list[str]:
    """The sequences a command works on: those named, or those of a split of the label config.

    Exactly one of `split` and `sequences` must be given; named sequences need not belong to
    any official split, so data outside the benchmark is served too.
    """
    if (split is None) == (sequences is None):
        raise ValueError("give either a split or a list of sequences, not both and not neither")
    if sequences is not None:
        names = [normalise_sequence(s) for s in sequences]
        if not names:
            raise ValueError("the list of sequences is empty")
        return sorted(dict.fromkeys(names))
    config = config or semantickitti()
    return list(config.split(split))


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
) -> Discovery:
    """List the scans of `sequences` under `root`, sorted, matched to their labels by name.

    Label files found are always attached; with `with_labels` they are required, and a scan
    without a label file and a label file without a scan are problems. A missing or empty sequence folder is a problem unless `missing_ok` (partial copies).
    """
    root = Path(root)
    result = Discovery(root=root, sequences=[])
    for seq in sequences:
        vdir = velodyne_dir(root, seq)
        if not vdir.is_dir():
            if not missing_ok:
                result.problems.append(f"{vdir} does not exist (sequence {seq} is missing)")
            continue
        result.sequences.append(seq)
        scans = _stems(vdir, ".bin")
        if not scans and not missing_ok:
            result.problems.append(f"{vdir} holds no .bin scan")
        labels = _stems(labels_dir(root, seq), ".label")
        if with_labels:
            for stem in sorted(scans.keys() - labels.keys()):
                result.problems.append(
                    f"{labels_dir(root, seq) / (stem + '.label')} is missing "
                    f"(scan {seq}/{stem} has no ground truth)"
                )
            for stem in sorted(labels.keys() - scans.keys()):
                result.problems.append(
                    f"{labels[stem]} has no matching scan {vdir / (stem + '.bin')}"
                )
        for stem in sorted(scans):
            result.scans.append(ScanEntry(seq, stem, scans[stem], labels.get(stem)))
    return result
