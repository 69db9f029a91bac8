"""JSON tables read within bounds: a table is data, never a reason to take unbounded memory or time.

A version's tables (nuScenes' `sample_data.json`, ...) come from whoever made the tree or the
upload. Each is read only if it is a regular file no larger than its table's limit (`TABLE_LIMITS`,
a few times the largest real table of that kind; `RANGERET_TABLE_LIMITS="sample_data=8GiB,
category=2MiB"` changes them), and only if it holds at most one JSON value per
`MIN_BYTES_PER_VALUE` bytes (real records spend 15 or more: a file of empty objects would take
twenty times its size once parsed). Then its records are decoded one at a time and only those a
caller selects are kept, so a parsed table holds little more than what its reader needs. A record
nested deeper than Python's JSON reader goes is refused in one sentence, as is every other fault.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rangeret.exceptions import DatasetError, InputError, InputFileMissing
from rangeret.io.regular_files import read_regular

#: The variable that changes the tables' size limits: `name=SIZE` pairs, comma-separated.
LIMITS_VARIABLE = "RANGERET_TABLE_LIMITS"
#: The largest file of each table read, in bytes: about four times v1.0-trainval's (its
#: sample_data.json is about 1.2 GB for 2.6 million records, calibrated_sensor.json a few MB).
TABLE_LIMITS = {
    "category": 1 << 20,
    "sensor": 1 << 20,
    "calibrated_sensor": 32 << 20,
    "scene": 8 << 20,
    "sample": 64 << 20,
    "sample_data": 5 << 30,
    "lidarseg": 32 << 20,
    "panoptic": 32 << 20,
}
#: The limit of a table not listed above.
DEFAULT_LIMIT = 64 << 20
#: The fewest bytes per JSON value (separators and brackets counted) a table may spend.
MIN_BYTES_PER_VALUE = 6
_UNITS = {"": 1, "B": 1, "KIB": 1 << 10, "MIB": 1 << 20, "GIB": 1 << 30, "KB": 10**3}
_UNITS |= {"MB": 10**6, "GB": 10**9}
_SIZE = re.compile(r"^\s*([0-9]+)\s*([A-Za-z]*)\s*$")
_SPACE = re.compile(r"[ \t\n\r]*")
_DECODER = json.JSONDecoder()

#: Picks what to keep of record i: the record (or a part of it), or None to drop it.
Select = Callable[[int, dict[str, Any]], "dict[str, Any] | None"]


class TableError(DatasetError, ValueError):
    """A table that cannot be read or does not agree with the others; the message names it."""


def table_limits() -> dict[str, int]:
    """Each table's size limit: `TABLE_LIMITS`, changed by `RANGERET_TABLE_LIMITS`."""
    limits = dict(TABLE_LIMITS)
    given = os.environ.get(LIMITS_VARIABLE, "").strip()
    for pair in filter(None, (p.strip() for p in given.split(","))):
        name, _, size = pair.partition("=")
        match = _SIZE.match(size)
        unit = match.group(2).upper() if match else ""
        if not name.strip() or match is None or unit not in _UNITS:
            raise TableError(
                f"{LIMITS_VARIABLE} holds {pair!r}: write table=SIZE pairs such as "
                "sample_data=8GiB,category=2MiB"
            )
        limits[name.strip()] = int(match.group(1)) * _UNITS[unit]
    return limits


def read_table(path: Path, name: str, select: Select | None = None) -> list[dict[str, Any]]:
    """The records of table `name` at `path` (a JSON list of objects) that `select` keeps (all
    when None), within the bounds of the module; `TableError` naming the file otherwise."""
    limit = table_limits().get(name, DEFAULT_LIMIT)
    try:
        data = read_regular(path, f"the {name} table", limit)
    except InputFileMissing:
        raise TableError(f"{path} is missing (every version holds a {name} table)") from None
    except InputError as exc:
        raise TableError(f"{exc} ({LIMITS_VARIABLE} sets the limits)") from None
    except OSError as exc:
        raise TableError(f"{path} cannot be read: {exc.strerror or exc}") from exc
    values = data.count(b",") + data.count(b"{") + data.count(b"[")
    if values * MIN_BYTES_PER_VALUE > len(data) + 64:
        raise TableError(
            f"{path} holds {values:,} JSON values in {len(data):,} bytes, more than one per "
            f"{MIN_BYTES_PER_VALUE} bytes: not a table of records"
        )
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise TableError(f"{path} is not UTF-8 text: {exc.reason} at byte {exc.start}") from None
    del data
    return _records(text, path, select)


def _records(text: str, path: Path, select: Select | None) -> list[dict[str, Any]]:
    """The selected records of a table's text, decoded one at a time."""
    kept: list[dict[str, Any]] = []
    at = _SPACE.match(text).end()
    if text[at : at + 1] != "[":
        raise TableError(
            f"{path} is not a JSON table: a table is a list of records, and it does not start with '['"
        )
    at = _SPACE.match(text, at + 1).end()
    index = 0
    while text[at : at + 1] != "]":
        try:
            record, at = _DECODER.raw_decode(text, at)
        except RecursionError:
            raise TableError(f"{path}: record {index} nests deeper than a JSON table may") from None
        except json.JSONDecodeError as exc:
            raise TableError(f"{path} is not a JSON table: {exc}") from None
        if not isinstance(record, dict):
            raise TableError(f"{path}: record {index} is not an object")
        chosen = record if select is None else select(index, record)
        if chosen is not None:
            kept.append(chosen)
        index += 1
        at = _SPACE.match(text, at).end()
        if text[at : at + 1] == ",":
            at = _SPACE.match(text, at + 1).end()
            if text[at : at + 1] == "]":
                raise TableError(f"{path} is not a JSON table: a comma before its closing ']'")
        elif text[at : at + 1] != "]":
            raise TableError(
                f"{path} is not a JSON table: expected ',' or ']' after record {index - 1}"
            )
    if _SPACE.match(text, at + 1).end() != len(text):
        raise TableError(f"{path} is not a JSON table: data after its closing ']'")
    return kept
