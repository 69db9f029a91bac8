"""What jobs may hold: the queue's length and the disk the job folders use.

A job is admitted when fewer than `max_queued` jobs wait and the job folders, with what the
queued and running jobs are still expected to write, stay within `max_bytes`. A job expects to
write a prediction (4 bytes per point) and its copy in the predictions zip for every scan: that
estimate is reserved from the moment the job is queued until it finishes.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

from rangeret.dataset.layout import ScanEntry
from rangeret.io.scans import LABEL_BYTES, PointRecord
from service.jobs.errors import NoRoom, QueueFull


def expected_output_bytes(entries: Iterable[ScanEntry], record: PointRecord) -> int:
    """The bytes a job over `entries` writes: each scan's prediction and its copy in the zip."""
    points = sum(os.stat(e.scan_path).st_size // record.point_bytes for e in entries)
    return 2 * LABEL_BYTES * points


def folder_bytes(folder: Path) -> int:
    """The bytes of the files under `folder` (0 when it is gone); links are not followed."""
    total = 0
    stack = [folder]
    while stack:
        try:
            with os.scandir(stack.pop()) as found:
                for entry in found:
                    if entry.is_dir(follow_symlinks=False):
                        stack.append(Path(entry.path))
                    elif entry.is_file(follow_symlinks=False):
                        total += entry.stat(follow_symlinks=False).st_size
        except FileNotFoundError:
            continue
    return total


def queue_full(max_queued: int) -> QueueFull:
    """The refusal when `max_queued` jobs wait already."""
    return QueueFull(
        f"The gateway has {max_queued:,} jobs waiting, its limit (RANGERET_MAX_QUEUED_JOBS); "
        "try again when one has started.",
    )


def disk_short(need: int, free: int, folder: Path) -> NoRoom:
    """The refusal when a job's `need` is more than the disk of the job folders has free."""
    return NoRoom(
        f"The job needs about {need:,} bytes of disk and the disk of the job folders ({folder}) "
        f"has {free:,} bytes free; free space there, or try again later.",
    )


def disk_full(need: int, used: int, max_bytes: int) -> NoRoom:
    """The refusal when a job's `need` does not fit beside the `used` bytes."""
    return NoRoom(
        f"The job needs about {need:,} bytes of disk and the job folders hold or expect "
        f"{used:,} of their {max_bytes:,} bytes (RANGERET_MAX_JOB_BYTES); remove finished jobs "
        "or try again later.",
    )
