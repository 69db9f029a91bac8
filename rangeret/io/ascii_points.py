"""The rows of an ASCII point body (PCD `DATA ascii`, PLY `format ascii`) as one structured array.

numpy's text reader parses the rows straight into an array of the header's record, so a body
decodes into one buffer of its declared points times the record's bytes (which the caller has
bounded), whatever the text holds; integers are read exact. Only the first `count` rows are read
(a PLY's later elements follow its vertices).
"""

from __future__ import annotations

import io
import os
import re

import numpy as np

from rangeret.io.scans import ScanFormatError

_VALUE = re.compile(rb"\S")
#: numpy's words for a row of another width than the record.
_WIDTH = re.compile(r"requires (\d+) columns but (\d+) were found at row (\d+)")


def read_ascii_rows(
    data: bytes | memoryview,
    offset: int,
    count: int,
    dtype: np.dtype,
    *,
    source: str | os.PathLike[str],
    error: type[ScanFormatError],
    what: str,
) -> np.ndarray:
    """The first `count` rows of whitespace-separated values of `data` from `offset` as a
    structured array of `dtype`; `error` naming `source` and `what` the body is when a value does
    not fit its field or there are fewer rows."""
    if count == 0 or not _VALUE.search(data, offset):
        rows = np.empty(0, dtype=dtype)
    else:
        stream = io.BytesIO(data)
        stream.seek(offset)
        try:
            rows = np.loadtxt(stream, dtype=dtype, comments=None, max_rows=count, ndmin=1)
        except ValueError as exc:
            raise error(source, f"the {what} cannot be read ({_reason(exc)})") from exc
    if len(rows) < count:
        raise error(
            source,
            f"the {what} holds {len(rows):,} point{'' if len(rows) == 1 else 's'}, the header "
            f"declares {count:,} (the file is truncated)",
        )
    return rows


def _reason(exc: ValueError) -> str:
    """numpy's reason a row could not be read, as a clause."""
    text = str(exc)
    width = _WIDTH.search(text)
    if width:
        need, got, row = width.groups()
        return f"row {row} holds {got} values, a point {need}; the file is truncated or malformed"
    return text.split("; use `usecols`")[0].rstrip(".")
