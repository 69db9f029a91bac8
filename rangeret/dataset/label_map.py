"""Label maps: which raw id of the target profile each raw id of a source dataset becomes.

A label map is a YAML mapping `source raw id: target raw id` (many to one), read with the
project's bounded YAML loader and checked against the target profile: ids are integers 0..65535
and every target id is one of the target's raw labels. Without a map raw ids travel unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rangeret.dataset.fields import is_int
from rangeret.dataset.labels import SEMANTIC_MASK
from rangeret.dataset.profiles import DatasetProfile
from rangeret.exceptions import ConfigError, InputError


class LabelMapError(ConfigError, ValueError):
    """A label map file that cannot be used; the message names the file and the id."""


class UnknownLabelError(InputError, ValueError):
    """A scan holding a raw id that the target profile or the label map does not know."""


@dataclass(frozen=True)
class LabelMap:
    """Source raw id -> target raw id, and the file it was read from (None: built in code)."""

    mapping: dict[int, int]
    path: str | None = None
    _lut: np.ndarray = field(init=False, repr=False, compare=False)
    _known: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        lut = np.zeros(SEMANTIC_MASK + 1, dtype=np.uint32)
        known = np.zeros(SEMANTIC_MASK + 1, dtype=bool)
        for source, target in self.mapping.items():
            lut[source], known[source] = target, True
        object.__setattr__(self, "_lut", lut)
        object.__setattr__(self, "_known", known)

    def missing(self, ids: np.ndarray) -> np.ndarray:
        """Those of the raw `ids` (sorted, unique) that the map does not list."""
        return ids[~self._known[ids]]

    def apply(self, semantic: np.ndarray) -> np.ndarray:
        """The target raw ids (uint32) of source raw ids that the map lists."""
        return self._lut[semantic]

    def to_dict(self) -> dict[str, object]:
        """The map as adapt.json records it: its file and its mapping."""
        return {"path": self.path, "mapping": {str(k): v for k, v in sorted(self.mapping.items())}}


def load_label_map(path: Path | str, target: DatasetProfile) -> LabelMap:
    """The label map in the YAML file `path`, checked against the target profile's raw labels;
    a `LabelMapError` naming the file and the id otherwise."""
    from rangeret.io.bounded_yaml import read_yaml

    data = read_yaml(path, "the label map", LabelMapError)
    if not isinstance(data, dict):
        raise LabelMapError(
            f"{path}: must be a mapping of source raw id: target raw id, got {type(data).__name__}"
        )
    if not data:
        raise LabelMapError(f"{path}: maps no raw id")
    known = target.labels.raw_to_class
    mapping: dict[int, int] = {}
    for source, value in data.items():
        if not is_int(source) or not 0 <= source <= SEMANTIC_MASK:
            raise LabelMapError(f"{path}: {source!r}: a source raw id must be an integer 0..65535")
        if not is_int(value) or not 0 <= value <= SEMANTIC_MASK:
            raise LabelMapError(
                f"{path}: {source}: the target raw id must be an integer 0..65535, got {value!r}"
            )
        if value not in known:
            raise LabelMapError(
                f"{path}: {source}: {value} is not a raw id of the {target.name} profile's labels"
            )
        mapping[source] = value
    return LabelMap(mapping, str(path))


def target_labels(
    labels: np.ndarray, target: DatasetProfile, label_map: LabelMap | None, scan: str
) -> np.ndarray:
    """The scan's uint32 labels as the target's raw ids, instances kept in the high 16 bits.

    Without a map every raw id that occurs must be one of the target's raw labels; with one, it
    must be listed in the map. Otherwise an `UnknownLabelError` naming the first such id and
    the scan.
    """
    labels = np.asarray(labels).astype(np.uint32, copy=False)
    semantic = labels & np.uint32(SEMANTIC_MASK)
    ids = np.unique(semantic)
    if label_map is None:
        unknown = [i for i in ids.tolist() if i not in target.labels.raw_to_class]
        if unknown:
            raise UnknownLabelError(
                f"{scan}: raw id {unknown[0]} is not a raw id of the {target.name} profile's "
                "labels; map the source's ids to the target's with --label-map"
            )
        return labels
    missing = label_map.missing(ids)
    if missing.size:
        raise UnknownLabelError(
            f"{scan}: raw id {int(missing[0])} is not in the label map {label_map.path}"
        )
    return label_map.apply(semantic) | (labels & ~np.uint32(SEMANTIC_MASK))
