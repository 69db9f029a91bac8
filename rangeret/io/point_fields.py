"""Named point fields (of a PCD, PLY or LAS file, or a PointCloud2 message) as a profile's record.

A file or a message names its fields; a profile's point record names the float32 values the
network reads (`x, y, z, remission`, or `x, y, z, intensity, laser_id`). Each record value is
taken from the field of the same name, else from the first field present among its aliases
(`intensity` for `remission`, `ring` for `laser_id`, ...), else from a field named on the command
line (`--field remission=reflectivity`). A cloud with no reflectance field gets the profile's
fill value (`DatasetProfile.reflectance_fill`); every other value must be there. Points whose
values are not all finite (the NaN returns of an organised cloud) stay in place and are marked
invalid: they are labelled unlabelled, so a cloud keeps one label per point.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rangeret.exceptions import InputError
from rangeret.io.scans import PointRecord

#: The record values a reflectance may fill, and the fields read as each record value when the
#: source has no field of the value's own name, in order of preference.
REFLECTANCE = ("remission", "intensity")
ALIASES: dict[str, tuple[str, ...]] = {
    "remission": ("remission", "intensity", "reflectance", "reflectivity", "i"),
    "intensity": ("intensity", "remission", "reflectance", "reflectivity", "i"),
    "laser_id": ("laser_id", "ring", "laser", "channel", "line"),
    "ring": ("ring", "laser_id", "laser", "channel", "line"),
}


class PointFieldsError(InputError, ValueError):
    """A cloud whose fields cannot fill the profile's point record, or a bad `--field` option."""


def parse_field_overrides(items: Sequence[str] | None, *, record: PointRecord) -> dict[str, str]:
    """`--field NAME=FIELD` options as {record value: source field}; a malformed one, or a NAME
    that the record does not hold, is a PointFieldsError naming it."""
    overrides: dict[str, str] = {}
    for item in items or ():
        name, sep, source = item.partition("=")
        name, source = name.strip(), source.strip()
        if not sep or not name or not source:
            raise PointFieldsError(f"--field {item!r}: expected NAME=FIELD, e.g. remission=i")
        if name not in record.fields:
            raise PointFieldsError(
                f"--field {item!r}: {name!r} is not a value of the point record "
                f"({', '.join(record.fields)})"
            )
        overrides[name] = source
    return overrides


@dataclass(frozen=True)
class RecordPoints:
    """A cloud as the profile's record: float32 (N, record fields), in the source's point order."""

    points: np.ndarray
    #: True for the points whose values are all finite (the ones the network labels).
    valid: np.ndarray
    #: For each record value, the source field it was read from, or `fill V` for a filled one.
    sources: dict[str, str] = field(default_factory=dict)

    @property
    def num_points(self) -> int:
        """Points of the cloud, the invalid ones included."""
        return len(self.points)

    @property
    def num_invalid(self) -> int:
        """Points left unlabelled because a value is NaN or infinite."""
        return int(self.num_points - np.count_nonzero(self.valid))

    def describe(self) -> dict[str, Any]:
        """How the record was filled, for run records and logs."""
        return {"fields": dict(self.sources), "invalid_points": self.num_invalid}


def find_field(
    name: str, available: Sequence[str], overrides: Mapping[str, str] | None = None
) -> str | None:
    """The source field read as record value `name`: the override, its own name or an alias."""
    if overrides and name in overrides:
        return overrides[name] if overrides[name] in available else None
    for candidate in ALIASES.get(name, (name,)):
        if candidate in available:
            return candidate
    lowered = {a.lower(): a for a in available}
    for candidate in ALIASES.get(name, (name,)):
        if candidate.lower() in lowered:
            return lowered[candidate.lower()]
    return None


def to_record(
    columns: Mapping[str, np.ndarray],
    *,
    record: PointRecord,
    source: str,
    reflectance_fill: float,
    overrides: Mapping[str, str] | None = None,
) -> RecordPoints:
    """The cloud of named one-value-per-point `columns` as `record`'s float32 array.

    `reflectance_fill` is what a cloud with no reflectance field gets; a missing position or
    laser id, a field named by `overrides` that the cloud lacks, or columns of different lengths
    are a PointFieldsError naming `source`.
    """
    available = list(columns)
    lengths = {len(np.asarray(columns[name])) for name in available}
    if len(lengths) > 1:
        raise PointFieldsError(f"{source}: its fields hold different numbers of points")
    n = lengths.pop() if lengths else 0
    points = np.empty((n, record.num_fields), dtype=np.float32)
    sources: dict[str, str] = {}
    for i, name in enumerate(record.fields):
        found = find_field(name, available, overrides)
        if found is None and overrides and name in overrides:
            raise PointFieldsError(
                f"{source}: has no field {overrides[name]!r} (named by --field {name}=...); "
                f"its fields: {', '.join(available) or 'none'}"
            )
        if found is None:
            if name in REFLECTANCE:
                points[:, i] = reflectance_fill
                sources[name] = f"fill {reflectance_fill:g}"
                continue
            aliases = ALIASES.get(name, (name,))
            raise PointFieldsError(
                f"{source}: has no {' or '.join(aliases)} field for the record's {name!r} "
                f"(its fields: {', '.join(available) or 'none'}; name one with --field {name}=FIELD)"
            )
        values = np.asarray(columns[found])
        if values.ndim != 1:
            raise PointFieldsError(f"{source}: field {found!r} holds more than one value per point")
        points[:, i] = values
        sources[name] = found
    valid = np.ones(n, dtype=bool)
    for i in range(record.num_fields):  # column by column: a row-wise all() is ten times slower
        valid &= np.isfinite(points[:, i])
    return RecordPoints(points=points, valid=valid, sources=sources)
