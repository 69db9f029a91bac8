"""Bounds on what a point-cloud file may decode to, checked from its header before any allocation.

A header declares a file's points and the bytes of each one (a PCD's fields' SIZE x COUNT, a PLY's
vertex properties, a LAS point record, the profile's record for a `.bin`). `DecodeLimits.check`
refuses a file whose points, times the wider of its point and the profile's record (what the
reader and the record it fills hold), pass `max_decoded_bytes`, or whose points pass
`max_points`, with a `DecodeLimitError` naming the bound; the readers then decode into at most
one buffer of that size. The gateway takes the bounds from RANGERET_MAX_DECODED_BYTES and
RANGERET_MAX_POINTS; `rangeret predict --files` and `rangeret view` from --max-decoded-bytes,
with the same default.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

from rangeret.io.scans import PointRecord, ScanFormatError

MIB = 1 << 20
#: What a file may decode to unless told otherwise: 2,000,000 points (the gateway's default
#: RANGERET_MAX_POINTS) of 128 bytes, twice the widest real LiDAR point records (about 64 bytes).
DEFAULT_MAX_DECODED_BYTES = 256 * MIB
#: The most values one point may hold (a PCD's fields with their COUNTs): each becomes a column.
MAX_POINT_VALUES = 4096
#: How the command line names the decoded bound.
DECODED_OPTION = "--max-decoded-bytes"


class DecodeLimitError(ScanFormatError):
    """A file whose header declares more than a bound allows, refused before it is decoded."""


@dataclass(frozen=True)
class Declared:
    """What a file's header declares: its points and the bytes of one point."""

    points: int
    point_bytes: int

    def decoded_bytes(self, record: PointRecord) -> int:
        """Bytes the decoded points take: the wider of the file's point and the record."""
        return self.points * max(self.point_bytes, record.point_bytes)


@dataclass(frozen=True)
class DecodeLimits:
    """The bounds a file is decoded within, and the names messages give them."""

    max_decoded_bytes: int = DEFAULT_MAX_DECODED_BYTES
    max_points: int | None = None
    decoded_name: str = DECODED_OPTION
    points_name: str = "the point limit"

    def __post_init__(self) -> None:
        if self.max_decoded_bytes < 1 or (self.max_points is not None and self.max_points < 1):
            raise ValueError("decode limits must be positive")

    def check(
        self, declared: Declared, *, record: PointRecord, source: str | os.PathLike[str]
    ) -> None:
        """`DecodeLimitError` naming `source` when the declared points or bytes pass a bound."""
        points = declared.points
        if self.max_points is not None and points > self.max_points:
            raise DecodeLimitError(
                source,
                f"declares {points:,} points, over the limit of {self.max_points:,} "
                f"({self.points_name})",
            )
        decoded = declared.decoded_bytes(record)
        if decoded > self.max_decoded_bytes:
            width = max(declared.point_bytes, record.point_bytes)
            raise DecodeLimitError(
                source,
                f"would decode to {decoded:,} bytes ({points:,} points of {width:,} bytes), over "
                f"the limit of {self.max_decoded_bytes:,} ({self.decoded_name})",
            )


#: The bounds of a run that names none: the default decoded bytes, no point limit.
DEFAULT_LIMITS = DecodeLimits()


def check_point_values(values: int, source: str | os.PathLike[str], what: str) -> None:
    """`DecodeLimitError` when a point would hold more than `MAX_POINT_VALUES` values."""
    if values > MAX_POINT_VALUES:
        raise DecodeLimitError(
            source,
            f"declares {values:,} values per point ({what}), over the limit of "
            f"{MAX_POINT_VALUES:,} a point may hold",
        )
