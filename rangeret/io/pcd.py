"""PCD (Point Cloud Library) files: the header read here, the data decoded and encoded by pypcd4.

The header is parsed before any data is touched, so that the declared point count (`POINTS`, else
`WIDTH * HEIGHT`) can refuse a file before a `binary_compressed` body is decompressed, and so that
a truncated body is named as such. Fields named `_` are padding and are not columns; a field with
`COUNT n > 1` gives the columns `NAME__0000` .. `NAME__n-1`. pypcd4 (BSD-3-Clause) comes with the
`files` extra. ASCII output is written here with enough digits for every value to read back exact.
"""

from __future__ import annotations

import io
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from rangeret.extras import require_extra
from rangeret.io.scans import ScanFormatError

#: The encodings of a PCD body.
ENCODINGS = ("ascii", "binary", "binary_compressed")
#: Header keys, in the order the format requires.
KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS")
#: (TYPE, SIZE) of a PCD field and its numpy type.
NUMPY_TYPES = {
    ("F", 4): "<f4", ("F", 8): "<f8",
    ("U", 1): "u1", ("U", 2): "<u2", ("U", 4): "<u4", ("U", 8): "<u8",
    ("I", 1): "i1", ("I", 2): "<i2", ("I", 4): "<i4", ("I", 8): "<i8",
}  # fmt: skip
#: Bytes of a header read before it must have ended.
HEADER_LIMIT = 64 << 10


class PcdFormatError(ScanFormatError):
    """A PCD file (or body) that cannot be read, naming the source and the problem."""


@dataclass(frozen=True)
class PcdHeader:
    """What a PCD header declares, and where its data starts."""

    fields: tuple[str, ...]
    sizes: tuple[int, ...]
    types: tuple[str, ...]
    counts: tuple[int, ...]
    width: int
    height: int
    points: int
    encoding: str
    data_offset: int

    @property
    def dtype(self) -> np.dtype:
        """The numpy record of one point (padding fields under their own `_N` names)."""
        items = []
        for i, (name, size, kind, count) in enumerate(
            zip(self.fields, self.sizes, self.types, self.counts, strict=True)
        ):
            base = NUMPY_TYPES[(kind, size)]
            name = f"_{i}" if name == "_" else name
            items += (
                [(name, base)] if count == 1 else [(f"{name}__{c:04d}", base) for c in range(count)]
            )
        return np.dtype(items)


def is_pcd(head: bytes) -> bool:
    """Whether bytes start like a PCD header (`# .PCD`, `VERSION` or `FIELDS`)."""
    return head.startswith((b"# .PCD", b"#.PCD", b"VERSION", b"FIELDS"))


def parse_header(data: bytes | memoryview, source: str) -> PcdHeader:
    """The header of a PCD file's bytes (only its first lines are read); PcdFormatError when a
    key is missing or malformed or the fields' lists disagree."""
    head = bytes(data[:HEADER_LIMIT])
    values: dict[str, list[str]] = {}
    offset = 0
    while True:
        end = head.find(b"\n", offset)
        if end < 0:
            raise PcdFormatError(source, "the PCD header has no DATA line (not a PCD file?)")
        try:
            line = head[offset:end].decode("ascii").strip()
        except UnicodeDecodeError:
            raise PcdFormatError(source, "the PCD header is not ASCII text") from None
        offset = end + 1
        if not line or line.startswith("#"):
            continue
        key, *words = line.split()
        if key.upper() == "DATA":
            encoding = words[0].lower() if words else ""
            break
        values[key.upper()] = words
    if encoding not in ENCODINGS:
        raise PcdFormatError(source, f"DATA {encoding!r} is not one of {', '.join(ENCODINGS)}")
    return _header(values, encoding, offset, source)


def _header(values: dict[str, list[str]], encoding: str, offset: int, source: str) -> PcdHeader:
    """The checked header of the key lines `values`."""
    fields = tuple(values.get("FIELDS", ()))
    if not fields:
        raise PcdFormatError(source, "the PCD header has no FIELDS")
    n = len(fields)
    try:
        sizes = tuple(int(v) for v in values.get("SIZE", ()))
        counts = tuple(int(v) for v in values.get("COUNT", ["1"] * n))
        width = int(values.get("WIDTH", ["0"])[0])
        height = int(values.get("HEIGHT", ["1"])[0])
        points = int(values.get("POINTS", [str(width * height)])[0])
    except ValueError as exc:
        raise PcdFormatError(
            source, f"the PCD header holds a number that is not one ({exc})"
        ) from exc
    types = tuple(t.upper() for t in values.get("TYPE", ()))
    for key, got in (("SIZE", sizes), ("TYPE", types), ("COUNT", counts)):
        if len(got) != n:
            raise PcdFormatError(source, f"the PCD header lists {n} FIELDS but {len(got)} {key}")
    for name, kind, size, count in zip(fields, types, sizes, counts, strict=True):
        if (kind, size) not in NUMPY_TYPES:
            raise PcdFormatError(
                source, f"field {name!r} has TYPE {kind} SIZE {size}, not a PCD type"
            )
        if count < 1:
            raise PcdFormatError(source, f"field {name!r} has COUNT {count}")
    named = [f for f in fields if f != "_"]
    if len(set(named)) != len(named):
        raise PcdFormatError(source, f"the PCD header names a field twice ({' '.join(fields)})")
    if min(width, height, points) < 0 or (width * height and points != width * height):
        raise PcdFormatError(
            source, f"the PCD header declares POINTS {points} but WIDTH {width} x HEIGHT {height}"
        )
    return PcdHeader(fields, sizes, types, counts, width, height, points, encoding, offset)


def declared_points(data: bytes | memoryview, source: str) -> int:
    """The points a PCD declares, from its header alone (nothing decompressed)."""
    return parse_header(data, source).points


@dataclass(frozen=True)
class PcdCloud:
    """A decoded PCD: its header and its points as one structured array (padding included)."""

    header: PcdHeader
    array: np.ndarray

    def columns(self) -> dict[str, np.ndarray]:
        """Each field as a 1-D array, padding left out."""
        names = self.array.dtype.names or ()
        return {n: self.array[n] for n in names if not _is_padding(n)}


def _is_padding(name: str) -> bool:
    return name.startswith("_") and name[1:].isdigit()


def read_pcd(data: bytes | memoryview, source: str) -> PcdCloud:
    """Decode a PCD file's bytes (any encoding); PcdFormatError when the body is truncated or
    cannot be decoded."""
    header = parse_header(data, source)
    require_extra("reading PCD files", "files")
    from pypcd4 import PointCloud

    dtype = header.dtype
    body = memoryview(data)[header.data_offset :]
    _check_body(header, body, dtype, source)
    if header.points == 0:
        return PcdCloud(header, np.empty(0, dtype=dtype))
    stream = io.BytesIO(_pypcd4_header(header).encode("ascii") + bytes(body))
    try:
        cloud = PointCloud.from_fileobj(stream)
    except (ValueError, RuntimeError, TypeError, KeyError, struct.error, OSError) as exc:
        raise PcdFormatError(
            source, f"the {header.encoding} PCD data cannot be decoded ({exc})"
        ) from exc
    array = np.asarray(cloud.pc_data)
    if len(array) != header.points:
        raise PcdFormatError(
            source,
            f"the {header.encoding} PCD data holds {len(array)} points, the header declares "
            f"{header.points} (the file is truncated)",
        )
    out = np.empty(header.points, dtype=dtype)
    for ours, theirs in zip(dtype.names, array.dtype.names, strict=True):
        out[ours] = array[theirs]
    return PcdCloud(header, out)


def _check_body(header: PcdHeader, body: memoryview, dtype: np.dtype, source: str) -> None:
    """Refuse a binary body shorter than its points, or a compressed one whose sizes are wrong,
    before anything is decoded."""
    need = header.points * dtype.itemsize
    if header.encoding == "binary" and len(body) < need:
        raise PcdFormatError(
            source,
            f"holds {len(body)} bytes of binary PCD data, {header.points} points need {need} "
            "(the file is truncated)",
        )
    if header.encoding == "binary_compressed" and header.points:
        if len(body) < 8:
            raise PcdFormatError(source, "the compressed PCD data has no size words (truncated)")
        compressed, uncompressed = struct.unpack("<II", bytes(body[:8]))
        if uncompressed != need:
            raise PcdFormatError(
                source,
                f"the compressed PCD data unpacks to {uncompressed} bytes, {header.points} points "
                f"need {need}",
            )
        if len(body) - 8 < compressed:
            raise PcdFormatError(
                source,
                f"holds {len(body) - 8} bytes of compressed PCD data, its size word says "
                f"{compressed} (the file is truncated)",
            )


def _pypcd4_header(header: PcdHeader, encoding: str | None = None, extra: tuple = ()) -> str:
    """A normalised header (every key present) for pypcd4, with `extra` (name, TYPE, SIZE) fields."""
    fields = list(header.fields) + [e[0] for e in extra]
    types = list(header.types) + [e[1] for e in extra]
    sizes = list(header.sizes) + [e[2] for e in extra]
    counts = list(header.counts) + [1] * len(extra)
    lines = [
        "VERSION 0.7",
        "FIELDS " + " ".join(fields),
        "SIZE " + " ".join(map(str, sizes)),
        "TYPE " + " ".join(types),
        "COUNT " + " ".join(map(str, counts)),
        f"WIDTH {header.width if header.width * header.height == header.points else header.points}",
        f"HEIGHT {header.height if header.width * header.height == header.points else 1}",
        "VIEWPOINT 0 0 0 1 0 0 0",
        f"POINTS {header.points}",
        f"DATA {encoding or header.encoding}",
    ]
    return "\n".join(lines) + "\n"


def labelled_pcd_bytes(cloud: PcdCloud, labels: np.ndarray, confidence: np.ndarray) -> bytes:
    """The PCD again, in its own encoding, with `label` (uint32) and `confidence` (float32) fields
    added (replacing fields of those names)."""
    require_extra("writing PCD files", "files")
    from pypcd4 import Encoding, MetaData, PointCloud

    kept = [i for i, f in enumerate(cloud.header.fields) if f not in ("label", "confidence")]
    header = _subset(cloud.header, kept)
    names = [n for n in cloud.array.dtype.names if _base_name(n) not in ("label", "confidence")]
    dtype = np.dtype(
        [(n, cloud.array.dtype[n]) for n in names] + [("label", "<u4"), ("confidence", "<f4")]
    )
    array = np.empty(len(cloud.array), dtype=dtype)
    for n in names:
        array[n] = cloud.array[n]
    array["label"], array["confidence"] = labels, confidence
    text = _pypcd4_header(header, extra=(("label", "U", 4), ("confidence", "F", 4)))
    if header.encoding == "ascii":
        return text.encode("ascii") + _ascii_rows(array)
    metadata = MetaData.parse_header(text.splitlines())
    out = io.BytesIO()
    PointCloud(metadata, array).save(out, encoding=Encoding(header.encoding))
    return out.getvalue()


def _base_name(name: str) -> str:
    return name.split("__")[0] if "__" in name else name


def _subset(header: PcdHeader, kept: list[int]) -> PcdHeader:
    """The header with only the fields at `kept`."""

    def pick(values: tuple[Any, ...]) -> tuple[Any, ...]:
        return tuple(values[i] for i in kept)

    return PcdHeader(
        pick(header.fields), pick(header.sizes), pick(header.types), pick(header.counts),
        header.width, header.height, header.points, header.encoding, header.data_offset,
    )  # fmt: skip


def _ascii_rows(array: np.ndarray) -> bytes:
    """One line per point, each value with the digits that read back exact."""
    formats = []
    for name in array.dtype.names:
        kind = array.dtype[name]
        formats.append("%.9g" if kind == np.float32 else "%.17g" if kind.kind == "f" else "%d")
    out = io.BytesIO()
    np.savetxt(out, array, fmt=formats, delimiter=" ")
    return out.getvalue()
