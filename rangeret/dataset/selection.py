"""What a command or a job reads of a dataset, chosen once where it starts: one `DatasetSelection`.

It holds the dataset's ROOT, the sequences chosen (named, or those of a split), the split they
were chosen by and, for a layout of tables, the version folder; every step after that (listing
scans, evaluating, archiving) takes the selection instead of loose `version` and `split` values.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path

from rangeret.dataset.labels import LabelConfig
from rangeret.dataset.layout import (
    DatasetLayout,
    Discovery,
    ScanEntry,
    list_scans,
    resolve_sequences,
)


@dataclass(frozen=True)
class DatasetSelection:
    """A dataset ROOT, the sequences chosen in it, and how they were chosen."""

    root: Path
    sequences: tuple[str, ...]
    layout: DatasetLayout = field(compare=False, repr=False)
    #: The split the sequences were chosen by (a tables layout's predictions go to its folder);
    #: None where they were named.
    split: str | None = None
    #: A tables layout's version folder; None: the one ROOT holds.
    version: str | None = None
    #: Panoptic ground truth and predictions (objects as well as classes) instead of semantic.
    panoptic: bool = False

    def discover(self, with_labels: bool = False, missing_ok: bool = False) -> Discovery:
        """The scans of the selection and every problem found on the way (`with_labels`: label
        files are required; `missing_ok`: a missing sequence is no problem)."""
        return self.layout.discover(
            self.root,
            self.sequences,
            with_labels,
            missing_ok,
            version=self.version,
            split=self.split,
            panoptic=self.panoptic,
        )

    def scans(self, missing_ok: bool = False) -> list[ScanEntry]:
        """The scans of the selection, in order; a missing or empty sequence is an error naming it
        unless `missing_ok`."""
        return list_scans(
            self.root,
            self.sequences,
            missing_ok,
            layout=self.layout,
            version=self.version,
            split=self.split,
            panoptic=self.panoptic,
        )

    def missing(self) -> list[str]:
        """Those of the sequences that ROOT does not hold, in their order."""
        return self.layout.missing(self.root, self.sequences, version=self.version)

    @classmethod
    def named(
        cls, root: Path | str, sequences: Iterable[str | int], layout: DatasetLayout
    ) -> DatasetSelection:
        """The named `sequences` of `root` (ids as the layout writes them), no split, no version."""
        return cls(Path(root), tuple(layout.normalise(s) for s in sequences), layout)

    def archive_options(self) -> dict[str, str | None]:
        """The split and version a benchmark archive of this selection is for, as its options."""
        return {"split": self.split, "version": self.version}

    def only(self, sequences: Iterable[str]) -> DatasetSelection:
        """The same selection narrowed to `sequences`."""
        return replace(self, sequences=tuple(sequences))

    def for_task(self, panoptic: bool) -> DatasetSelection:
        """The same scans, for panoptic segmentation or for semantic segmentation only."""
        return replace(self, panoptic=panoptic)


def select_dataset(
    root: Path | str,
    *,
    layout: DatasetLayout,
    labels: LabelConfig,
    split: str | None = None,
    sequences: Iterable[str | int] | None = None,
    version: str | None = None,
) -> DatasetSelection:
    """The selection of exactly one of a `split` of `labels` and named `sequences` under `root`;
    a `version` for a layout without versions is a `DatasetLayoutError` saying so."""
    layout.check_version(version)
    chosen = resolve_sequences(split, sequences, labels=labels, layout=layout)
    return DatasetSelection(Path(root), tuple(chosen), layout, split, version)
