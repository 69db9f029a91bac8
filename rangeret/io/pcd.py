"""PCD (Point Cloud Library) files: the header and the data read here, labelled copies encoded by
pypcd4.

The header is parsed and bounded before any data is touched: a point may hold at most
`MAX_POINT_VALUES` values (its fields with their COUNTs), the declared points (`POINTS`, else
`WIDTH * HEIGHT`) times the point's bytes are what the caller's `DecodeLimits` bound, and a
truncated body is named as such. The data then decodes into at most one buffer: a `binary` body
is read in place, an `ascii` one parsed into one array, a `binary_compressed` one decompressed
(LZF, `rangeret.io.lzf_codec`) into one buffer whose fields are read in place (each value of a
field with `COUNT n > 1` stored as its own block, as pypcd4 writes them). Fields named `_` are
padding and are not columns; a field with `COUNT n > 1` gives the columns `NAME__0000` ..
`NAME__n-1`. pypcd4 and its LZF codec, python-neo-lzf (both BSD-3-Clause), come with the `files`
extra. ASCII output is written here with enough digits for every value to read back exact.
"""

from __future__ import annotations

import io
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from rangeret.extras import require_extra
from rangeret.io.ascii_points import read_ascii_rows
from rangeret.io.decode_limits import Declared, check_point_values
from rangeret.io.lzf_codec import decompress_into
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
#: The name of a padding field.
PADDING = "_"


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
    def point_bytes(self) -> int:
        """Bytes of one point, padding included."""
        return sum(s * c for s, c in zip(self.sizes, self.counts, strict=True))

    def base_type(self, i: int) -> np.dtype:
        """The numpy type of one value of field `i`."""
        return np.dtype(NUMPY_TYPES[(self.types[i], self.sizes[i])])

    def column_names(self, i: int) -> list[str]:
        """The columns field `i` gives (`NAME`, or `NAME__0000` .. for a COUNT over 1)."""
        name, count = self.fields[i], self.counts[i]
        return [name] if count == 1 else [f"{name}__{c:04d}" for c in range(count)]

    def point_dtype(self) -> np.dtype:
        """One point as the body stores it: field `i` as `f{i}` (a subarray for COUNT > 1)."""
        return np.dtype(
            [
                (f"f{i}", self.base_type(i)) if c == 1 else (f"f{i}", self.base_type(i), (c,))
                for i, c in enumerate(self.counts)
            ]
        )

    def flat_dtype(self) -> np.dtype:
        """One point with every value its own field `v{k}`, in order (as pypcd4 writes it)."""
        kinds = [self.base_type(i) for i, count in enumerate(self.counts) for _ in range(count)]
        return np.dtype([(f"v{k}", kind) for k, kind in enumerate(kinds)])


def is_pcd(head: bytes) -> bool:
    """Whether bytes start like a PCD header (`# .PCD`, `VERSION` or `FIELDS`)."""
    return head.startswith((b"# .PCD", b"#.PCD", b"VERSION", b"FIELDS"))


def parse_header(data: bytes | memoryview, source: str) -> PcdHeader:
    """The header of a PCD file's bytes (only its first lines are read); PcdFormatError when a
    key is missing or malformed or the fields' lists disagree, `DecodeLimitError` when a point
    would hold more than `MAX_POINT_VALUES` values."""
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
    check_point_values(sum(counts), source, "its FIELDS with their COUNTs")
    if min(width, height, points) < 0 or (width * height and points != width * height):
        raise PcdFormatError(
            source, f"the PCD header declares POINTS {points} but WIDTH {width} x HEIGHT {height}"
        )
    header = PcdHeader(fields, sizes, types, counts, width, height, points, encoding, offset)
    _check_names(header, source)
    return header


def _check_names(header: PcdHeader, source: str) -> None:
    """PcdFormatError when two fields, once their COUNTs are expanded, give one column name."""
    named = [f for f in header.fields if f != PADDING]
    if len(set(named)) != len(named):
        raise PcdFormatError(
            source, f"the PCD header names a field twice ({' '.join(header.fields)})"
        )
    owner: dict[str, str] = {}
    for i, field in enumerate(header.fields):
        if field == PADDING:
            continue
        for column in header.column_names(i):
            other = owner.setdefault(column, field)
            if other != field:
                first, second = sorted((other, field), key=header.fields.index)
                raise PcdFormatError(
                    source,
                    f"the PCD fields {first!r} and {second!r} both give the column {column!r} "
                    "(a field with COUNT n gives NAME__0000 .. NAME__n-1)",
                )


def declared(data: bytes | memoryview, source: str) -> Declared:
    """The points a PCD declares and the bytes of each, from its header alone."""
    header = parse_header(data, source)
    return Declared(header.points, header.point_bytes)


def declared_points(data: bytes | memoryview, source: str) -> int:
    """The points a PCD declares, from its header alone (nothing decompressed)."""
    return parse_header(data, source).points


@dataclass(frozen=True)
class PcdCloud:
    """A decoded PCD: its header and each field's values ((N,), or (N, COUNT)), padding included."""

    header: PcdHeader
    values: tuple[np.ndarray, ...]

    def columns(self) -> dict[str, np.ndarray]:
        """Each field as 1-D arrays (a COUNT over 1 as one per value), padding left out."""
        out: dict[str, np.ndarray] = {}
        for i, field in enumerate(self.header.fields):
            if field == PADDING:
                continue
            names = self.header.column_names(i)
            if len(names) == 1:
                out[names[0]] = self.values[i]
            else:
                out.update((name, self.values[i][:, c]) for c, name in enumerate(names))
        return out

    @property
    def padding(self) -> int:
        """Padding values per point (fields named `_`, with their COUNTs)."""
        return sum(
            c for f, c in zip(self.header.fields, self.header.counts, strict=True) if f == PADDING
        )


def read_pcd(data: bytes | memoryview, source: str) -> PcdCloud:
    """Decode a PCD file's bytes (any encoding) into at most one buffer of its declared points;
    PcdFormatError when the body is truncated or cannot be decoded. The caller bounds the
    declared size (`declared`) first."""
    header = parse_header(data, source)
    require_extra("reading PCD files", "files")
    body = memoryview(data)[header.data_offset :]
    _check_body(header, body, source)
    n = header.points
    if header.encoding == "binary_compressed":
        return PcdCloud(header, _compressed_values(header, body, source) if n else _empty(header))
    point = header.point_dtype()
    if header.encoding == "binary":
        array = np.frombuffer(body, dtype=point, count=n)
    else:
        what = "ascii PCD data"
        array = read_ascii_rows(
            data, header.data_offset, n, point, source=source, error=PcdFormatError, what=what
        )
    return PcdCloud(header, tuple(array[f"f{i}"] for i in range(len(header.fields))))


def _empty(header: PcdHeader) -> tuple[np.ndarray, ...]:
    """Each field's values for no points."""
    array = np.empty(0, dtype=header.point_dtype())
    return tuple(array[f"f{i}"] for i in range(len(header.fields)))


def _compressed_values(header: PcdHeader, body: memoryview, source: str) -> tuple[np.ndarray, ...]:
    """Each field's values of a `binary_compressed` body: decompressed into one buffer, and each
    value's block of it read in place."""
    compressed, need = struct.unpack("<II", bytes(body[:8]))
    stream = np.frombuffer(body, dtype=np.uint8, count=compressed, offset=8)
    buffer = decompress_into(stream, need)
    if buffer is None:
        raise PcdFormatError(
            source,
            f"the compressed PCD data does not decompress to the {need:,} bytes its size word "
            "declares (its LZF stream is corrupt)",
        )
    n, offset, values = header.points, 0, []
    for i, count in enumerate(header.counts):
        kind = header.base_type(i)
        block = np.frombuffer(buffer, dtype=kind, count=n * count, offset=offset)
        values.append(block if count == 1 else block.reshape(count, n).T)
        offset += n * count * kind.itemsize
    return tuple(values)


def _check_body(header: PcdHeader, body: memoryview, source: str) -> None:
    """Refuse a binary body shorter than its points, or a compressed one whose sizes are wrong,
    before anything is decoded."""
    need = header.points * header.point_bytes
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


def labelled_pcd_bytes(
    cloud: PcdCloud,
    labels: np.ndarray,
    confidence: np.ndarray,
    instances: np.ndarray | None = None,
) -> bytes:
    """The PCD again, in its own encoding, with `label` (uint32) and `confidence` (float32) fields
    added, and given `instances`, `instance` (uint32) (replacing fields of those names)."""
    require_extra("writing PCD files", "files")
    from pypcd4 import Encoding, MetaData, PointCloud

    added = {"label": ("U", labels), "confidence": ("F", confidence)}
    if instances is not None:
        added["instance"] = ("U", instances)
    kept = [i for i, f in enumerate(cloud.header.fields) if f not in added]
    header = _subset(cloud.header, kept)
    flat = header.flat_dtype()
    kinds = {"U": "<u4", "F": "<f4"}
    dtype = np.dtype([*flat.descr, *((name, kinds[t]) for name, (t, _) in added.items())])
    array = np.empty(len(labels), dtype=dtype)
    column = 0
    for i in kept:
        values = cloud.values[i] if cloud.values[i].ndim == 2 else cloud.values[i][:, None]
        for c in range(values.shape[1]):
            array[f"v{column}"] = values[:, c]
            column += 1
    for name, (_, values) in added.items():
        array[name] = values
    text = _pypcd4_header(header, extra=tuple((name, t, 4) for name, (t, _) in added.items()))
    if header.encoding == "ascii":
        return text.encode("ascii") + _ascii_rows(array)
    metadata = MetaData.parse_header(text.splitlines())
    out = io.BytesIO()
    PointCloud(metadata, array).save(out, encoding=Encoding(header.encoding))
    return out.getvalue()


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
