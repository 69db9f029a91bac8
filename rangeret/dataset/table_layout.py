"""The tables layout: a dataset whose scans, labels and splits come from a version's tables.

nuScenes is laid out this way (`rangeret.dataset.nuscenes_tables` reads it): a sequence is a
scene, named as in scene.json (`scene-0103`), and a scan is a keyframe sweep, named by its
sample_data token. Predictions go where the nuScenes-lidarseg benchmark wants them:

    PRED/lidarseg/<split>/<sample_data token>_lidarseg.bin   one uint8 class index per point
    PRED/panoptic/<split>/<sample_data token>_panoptic.npz   with --panoptic: uint16 `data`,
                                                             1000 x class + instance per point
    PRED/confidence/<split>/<sample_data token>.npy          point confidences, when asked

The panoptic ground truth is the version's `panoptic.json` table and the `.npz` files it names.

The split folder is the split the command was given; with named scenes, the first split of the
profile that lists the scene among those of the version's family (`mini_*` for v1.0-mini, the
others for the rest), else the version's name.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

from rangeret.dataset.layout import DatasetLayoutError, Discovery, ScanEntry
from rangeret.dataset.nuscenes_tables import (
    NuScenesTables,
    find_version,
    read_tables,
    version_folders,
)
from rangeret.dataset.table_upload_rules import NuScenesRules
from rangeret.dataset.upload_rules import ArchiveRules
from rangeret.io.panoptic_labels import PANOPTIC_NPZ, THOUSANDS, NpzLabelFile, PanopticEncoding
from rangeret.io.scans import LabelFile, PointRecord

#: nuScenes-lidarseg's label and prediction files: one uint8 per point.
LIDARSEG_LABELS = LabelFile(1)
#: The table schemas this layout reads.
SCHEMAS = ("nuscenes",)


@dataclass(frozen=True)
class TableLayout:
    """Scenes and keyframe sweeps of a version's tables (`tables` names the schema, `channel`
    the sensor); `splits` and `raw_names` are the profile's, for the split folders and for
    checking that the tables' categories are the ones the profile's labels mean."""

    tables: str = "nuscenes"
    channel: str = "LIDAR_TOP"
    splits: Mapping[str, tuple[str, ...]] = field(default_factory=dict, compare=False, repr=False)
    raw_names: Mapping[int, str] = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        if self.tables not in SCHEMAS:
            raise DatasetLayoutError(
                f"layout.tables must be one of {', '.join(SCHEMAS)}, got {self.tables!r}"
            )
        if not self.channel:
            raise DatasetLayoutError("layout.channel must name a sensor channel")

    @property
    def folders(self) -> None:
        """None: a version's tables are not folders of sequences."""
        return None

    def versions(self, root: Path | str) -> list[str]:
        """The version folders ROOT holds (those with a scene.json), sorted."""
        return version_folders(root)

    def check_version(self, version: str | None) -> None:
        """Any version may be asked for; `open` says when ROOT does not hold it."""

    @property
    def label_file(self) -> LabelFile:
        """nuScenes-lidarseg's `_lidarseg.bin` files: one uint8 per point."""
        return LIDARSEG_LABELS

    @property
    def panoptic_encoding(self) -> PanopticEncoding:
        """nuScenes-panoptic's labels: 1000 x class + instance, in `_panoptic.npz` files."""
        return THOUSANDS

    @property
    def panoptic_file(self) -> NpzLabelFile:
        """nuScenes-panoptic's `_panoptic.npz` files: one uint16 array `data`."""
        return PANOPTIC_NPZ

    def normalise(self, name: str | int) -> str:
        """Scene names are kept as written (`scene-0103`)."""
        return str(name).strip()

    def to_dict(self) -> dict[str, Any]:
        """The profile's `layout` section."""
        return {"tables": self.tables, "channel": self.channel}

    def upload_rules(self, record: PointRecord) -> ArchiveRules:
        """An uploaded archive's rules: one version's tables, sweeps of `record` and label files,
        each kept at its own path (`rangeret.dataset.table_upload_rules`)."""
        return NuScenesRules(record, self)

    def open(self, root: Path | str, version: str | None = None) -> NuScenesTables:
        """The tables of ROOT's version (the one it holds, or `version`)."""
        return read_tables(root, find_version(root, version), self.channel)

    def list_sequences(self, root: Path | str, *, version: str | None = None) -> list[str]:
        """Every scene of the version, sorted."""
        return sorted(self.open(root, version).scenes)

    def missing(
        self, root: Path | str, sequences: Sequence[str], *, version: str | None = None
    ) -> list[str]:
        """Those of `sequences` that the version's tables do not hold, in their order."""
        scenes = self.open(root, version).scenes
        return [s for s in sequences if s not in scenes]

    def split_folder(self, scene: str, version: str) -> str:
        """The split folder of a scene's predictions when no split was given."""
        mini = version.endswith("mini")
        for name, scenes in self.splits.items():
            if name.startswith("mini") == mini and scene in scenes:
                return name
        return version

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
        """The keyframe sweeps of the scenes `sequences`, in scene order then time order; a
        scene the tables lack, a sweep file or (with `with_labels`) a label file that is not
        there, and categories other than the profile's are problems naming them. With
        `panoptic`, the ground truth is the `panoptic` table's and the predictions are
        `_panoptic.npz` files."""
        tables = self.open(root, version)
        result = Discovery(root=Path(root), sequences=[])
        result.problems.extend(self._category_problems(tables))
        for scene in sequences:
            frames = tables.scenes.get(scene)
            if frames is None:
                if not missing_ok:
                    result.problems.append(
                        f"{tables.table_dir / 'scene.json'} holds no scene {scene}"
                    )
                continue
            result.sequences.append(scene)
            folder = split or self.split_folder(scene, tables.version)
            for frame in frames:
                scan = tables.root / frame.filename
                truth = frame.panoptic_filename if panoptic else frame.label_filename
                label = None if truth is None else tables.root / truth
                if not scan.is_file():
                    result.problems.append(
                        f"{scan} is missing (the sweep of sample {frame.sample} of {scene})"
                    )
                    continue
                if label is not None and not label.is_file():
                    if with_labels:
                        result.problems.append(
                            f"{label} is missing (sweep {frame.token} of {scene} has no ground "
                            "truth)"
                        )
                    label = None
                elif label is None and with_labels:
                    table = "panoptic.json" if panoptic else "lidarseg.json"
                    result.problems.append(
                        f"{tables.table_dir / table} has no record for sweep "
                        f"{frame.token} of {scene} (no {'panoptic ' if panoptic else ''}ground "
                        "truth)"
                    )
                if panoptic:
                    prediction = f"panoptic/{folder}/{frame.token}_panoptic.npz"
                else:
                    prediction = f"lidarseg/{folder}/{frame.token}_lidarseg.bin"
                result.scans.append(
                    ScanEntry(
                        scene,
                        frame.token,
                        scan,
                        label,
                        prediction,
                        f"confidence/{folder}/{frame.token}.npy",
                        self.panoptic_file if panoptic else self.label_file,
                    )
                )
        return result

    def _category_problems(self, tables: NuScenesTables) -> list[str]:
        """Where category.json's indices name other classes than the profile's raw labels."""
        if not self.raw_names:
            return []
        path = tables.table_dir / "category.json"
        return [
            f"{path}: index {index} is {name!r}, but the profile's raw label {index} is "
            f"{self.raw_names.get(index)!r}"
            for index, name in sorted(tables.categories.items())
            if self.raw_names.get(index) != name
        ]


def prediction_split(entry: ScanEntry) -> str:
    """The split folder a tables layout's scan has its prediction in (`lidarseg/<split>/...`)."""
    return PurePosixPath(entry.prediction).parent.name
