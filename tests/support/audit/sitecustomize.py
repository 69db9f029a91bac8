"""Loaded at the start of every Python process whose PYTHONPATH begins with this folder: with
RANGERET_TEST_AUDIT_LOG set, an audit hook appends one line per read of a file whose name is in
RANGERET_TEST_AUDIT_FILES (comma-separated) and one per import of a `workers` module, each with
the process id, so a test can count what each process of a run read and imported."""

from __future__ import annotations

import os
import sys

_LOG = os.environ.get("RANGERET_TEST_AUDIT_LOG")
_NAMES = set(filter(None, os.environ.get("RANGERET_TEST_AUDIT_FILES", "").split(",")))
_busy = False


def _reads(mode: object, flags: object) -> bool:
    if isinstance(mode, str):
        return "r" in mode and "+" not in mode
    return isinstance(flags, int) and flags & os.O_ACCMODE == os.O_RDONLY


def _write(line: str) -> None:
    global _busy
    _busy = True
    try:
        with open(_LOG, "a") as log:
            log.write(f"{os.getpid()} {line}\n")
    finally:
        _busy = False


def _hook(event: str, args: tuple) -> None:
    if _busy:
        return
    if event == "open" and args and args[0] is not None and not isinstance(args[0], int):
        path = os.fsdecode(os.fspath(args[0]))
        if os.path.basename(path) in _NAMES and _reads(args[1], args[2]):
            _write(f"read {os.path.realpath(path)}")
    elif (
        event == "import"
        and args
        and isinstance(args[0], str)
        and (args[0] == "workers" or args[0].startswith("workers."))
    ):
        _write(f"import {args[0]}")


if _LOG:
    sys.addaudithook(_hook)
