"""`rangeret.io.regular_files`: what is not a regular file is refused by its kind before a byte
is read (a FIFO without blocking), a missing path is `InputFileMissing`, a size limit is checked
before reading, and a regular file is read whole."""

from __future__ import annotations

import os
import socket

import pytest

from rangeret.exceptions import InputFileMissing
from rangeret.io.regular_files import (
    FileTooLargeError,
    NotRegularFileError,
    open_regular,
    read_regular,
    require_regular,
)


def test_each_kind_is_named(tmp_path):
    os.mkfifo(tmp_path / "fifo")
    (tmp_path / "folder").mkdir()
    with socket.socket(socket.AF_UNIX) as unix:
        unix.bind(str(tmp_path / "socket"))
        kinds = {
            tmp_path / "fifo": "a FIFO (named pipe)",  # no writer: a blocking open would hang
            tmp_path / "folder": "a folder",
            tmp_path / "socket": "a socket",
            "/dev/zero": "a character device",
        }
        for path, kind in kinds.items():
            for check in (open_regular, require_regular):
                with pytest.raises(NotRegularFileError) as refused:
                    check(path, "a table")
                assert refused.value.kind == kind
                assert (
                    str(refused.value)
                    == f"{path} is {kind}, not a file: a table must be a regular file"
                )


def test_a_missing_file_a_limit_and_a_regular_file(tmp_path):
    with pytest.raises(InputFileMissing):
        read_regular(tmp_path / "none", "a table")
    (tmp_path / "t.json").write_bytes(b"[]" * 10)
    assert read_regular(tmp_path / "t.json", "a table", limit=20) == b"[]" * 10
    with pytest.raises(FileTooLargeError, match=r"is 20 bytes, more than the 19 that a table"):
        read_regular(tmp_path / "t.json", "a table", limit=19)
    assert require_regular(tmp_path / "t.json", "a table").st_size == 20
