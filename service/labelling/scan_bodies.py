"""The bodies POST /v1/scans takes: `.bin` point records, or a PCD, PLY, LAS or LAZ file.

The Content-Type names the format (`CONTENT_TYPES`); `application/octet-stream` is a `.bin` body
unless the body starts with a PCD, PLY or LAS signature. A file body is decoded off the event
loop by the library's one reader (`rangeret.io.point_files`), its header checked first against
the gateway's limits (`body_limits`: RANGERET_MAX_POINTS and RANGERET_MAX_DECODED_BYTES), so
that what would decode past them is a 413 before anything is allocated or decompressed. At most
`DECODE_SLOTS` bodies decode at once, so the memory decoding takes stays within a small multiple
of RANGERET_MAX_DECODED_BYTES however many requests arrive. Its fields fill the served profile's
point record as `rangeret predict --files` fills it; points with a NaN or infinite value are not
sent to the network and get the unlabelled raw id (confidence 0), so the answer keeps the body's
point order.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from rangeret.dataset.profiles import DatasetProfile
from rangeret.extras import MissingExtraError
from rangeret.io.decode_limits import DecodeLimitError, DecodeLimits
from rangeret.io.point_fields import PointFieldsError, to_record
from rangeret.io.point_files import decode_point_file, signature_format
from rangeret.io.scans import ScanFormatError
from service.http.errors import ApiError
from service.settings import Settings

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
#: File bodies decoded at once, each within RANGERET_MAX_DECODED_BYTES.
DECODE_SLOTS = 2
_decoding = threading.BoundedSemaphore(DECODE_SLOTS)


def body_format(media: str, head: bytes) -> str:
    """The format of a body of media type `media` (one of `CONTENT_TYPES`) starting with `head`."""
    return CONTENT_TYPES[media] or signature_format(head) or "bin"


def body_limits(settings: Settings) -> DecodeLimits:
    """What a file body may declare and decode to, named by the settings that bound it."""
    return DecodeLimits(
        max_decoded_bytes=settings.max_decoded_bytes,
        max_points=settings.max_points,
        decoded_name="RANGERET_MAX_DECODED_BYTES",
        points_name="RANGERET_MAX_POINTS",
    )


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


def decode_file_body(
    body: bytes, fmt: str, profile: DatasetProfile, limits: DecodeLimits
) -> FileBody:
    """Decode a file body into the profile's record, its header checked against `limits` first
    (call it off the event loop); 413 naming the limit a body would pass, 400 naming the
    problem when it cannot be decoded."""
    name = fmt.upper()
    try:
        with _decoding:
            return _decoded(body, fmt, profile, limits)
    except MissingExtraError as exc:
        raise ApiError(415, f"This gateway cannot read {name} bodies: {exc}.") from exc
    except DecodeLimitError as exc:
        raise ApiError(413, f"The {name} scan {exc.problem}.") from exc
    except ScanFormatError as exc:
        raise ApiError(400, f"The {name} scan is malformed: {exc.problem}.") from exc
    except PointFieldsError as exc:
        problem = str(exc).removeprefix(f"{SOURCE}: ")
        raise ApiError(
            400,
            f"The scan's fields do not fill the {profile.name} point record "
            f"({', '.join(profile.points.fields)}): it {problem}.",
        ) from exc


def _decoded(body: bytes, fmt: str, profile: DatasetProfile, limits: DecodeLimits) -> FileBody:
    """The body's valid points as the profile's record (its decoded columns freed on return)."""
    point_file = decode_point_file(body, fmt, record=profile.points, source=SOURCE, limits=limits)
    cloud = to_record(
        point_file.columns,
        record=profile.points,
        source=SOURCE,
        reflectance_fill=profile.reflectance_fill,
    )
    points = cloud.points if cloud.num_invalid == 0 else cloud.points[cloud.valid]
    return FileBody(np.ascontiguousarray(points), cloud.valid, point_file.format)
