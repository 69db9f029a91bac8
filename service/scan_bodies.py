"""The bodies POST /v1/scans takes: `.bin` point records, or a PCD, PLY, LAS or LAZ file.

The Content-Type names the format (`CONTENT_TYPES`); `application/octet-stream` is a `.bin` body
unless the body starts with a PCD, PLY or LAS signature. A file body's declared point count (the
PCD or LAS header, the PLY vertex count) is checked against the gateway's limit before anything is
decoded or decompressed. Its fields fill the served profile's point record as
`rangeret predict --files` fills it; points with a NaN or infinite value are not sent to the
network and get the unlabelled raw id (confidence 0), so the answer keeps the body's point order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rangeret.dataset.profiles import DatasetProfile
from rangeret.extras import MissingExtraError
from rangeret.io.point_fields import PointFieldsError, to_record
from rangeret.io.point_files import declared_points, decode_point_file, signature_format
from rangeret.io.scans import PointRecord, ScanFormatError
from service.errors import ApiError

OCTET = "application/octet-stream"
#: The media types a scan body may have, and the format each names (None: `.bin`, unless the
#: body's signature says otherwise).
CONTENT_TYPES: dict[str, str | None] = {
    OCTET: None,
    "application/x-pcd": "pcd",
    "application/x-ply": "ply",
    "application/ply": "ply",
    "application/vnd.las": "las",
    "application/vnd.laszip": "las",
}
#: How a body is named in answers.
SOURCE = "the scan"


def body_format(media: str, head: bytes) -> str:
    """The format of a body of media type `media` (one of `CONTENT_TYPES`) starting with `head`."""
    return CONTENT_TYPES[media] or signature_format(head) or "bin"


def check_declared(body: bytes, fmt: str, record: PointRecord, max_points: int) -> int:
    """The points a file body declares; 413 over `max_points`, 400 for an unreadable header."""
    try:
        declared = declared_points(body, fmt, record=record, source=SOURCE)
    except MissingExtraError as exc:
        raise ApiError(415, f"This gateway cannot read {fmt.upper()} bodies: {exc}.") from exc
    except ScanFormatError as exc:
        raise ApiError(400, f"The {fmt.upper()} scan is malformed: {exc.problem}.") from exc
    if declared > max_points:
        raise ApiError(
            413,
            f"The {fmt.upper()} scan declares {declared:,} points, over the limit of "
            f"{max_points:,}.",
        )
    return declared


@dataclass(frozen=True)
class FileBody:
    """A decoded file body: its valid points as the profile's record, and which they are."""

    points: np.ndarray
    valid: np.ndarray
    format: str

    @property
    def num_points(self) -> int:
        """Points of the body, the invalid ones included."""
        return len(self.valid)


def decode_file_body(body: bytes, fmt: str, profile: DatasetProfile) -> FileBody:
    """Decode a file body into the profile's record; 400 naming the problem when it cannot be."""
    try:
        point_file = decode_point_file(body, fmt, record=profile.points, source=SOURCE)
        cloud = to_record(
            point_file.columns,
            record=profile.points,
            source=SOURCE,
            reflectance_fill=profile.reflectance_fill,
        )
    except MissingExtraError as exc:
        raise ApiError(415, f"This gateway cannot read {fmt.upper()} bodies: {exc}.") from exc
    except ScanFormatError as exc:
        raise ApiError(400, f"The {fmt.upper()} scan is malformed: {exc.problem}.") from exc
    except PointFieldsError as exc:
        problem = str(exc).removeprefix(f"{SOURCE}: ")
        raise ApiError(
            400,
            f"The scan's fields do not fill the {profile.name} point record "
            f"({', '.join(profile.points.fields)}): it {problem}.",
        ) from exc
    points = cloud.points if cloud.num_invalid == 0 else cloud.points[cloud.valid]
    return FileBody(np.ascontiguousarray(points), cloud.valid, point_file.format)
