"""The HTTP answer to each refusal of the jobs package and of an uploaded archive's rules.

`service.jobs` and the library raise errors that say what went wrong; this table is the one
place that says which status each one is answered with.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from rangeret.dataset.upload_rules import ArchiveError, ArchiveTooLarge
from service.http.errors import ApiError
from service.jobs.errors import (
    BadJobRequest,
    JobInputError,
    NoRoom,
    NoSuchDataset,
    OutsideDataRoots,
    QueueFull,
)

#: The status of each refusal, the most specific first.
STATUSES: tuple[tuple[type[Exception], int], ...] = (
    (ArchiveTooLarge, 413),
    (ArchiveError, 400),
    (BadJobRequest, 400),
    (OutsideDataRoots, 403),
    (NoSuchDataset, 404),
    (QueueFull, 429),
    (NoRoom, 507),
)
#: The refusals `answered` turns into answers.
REFUSALS = (JobInputError, ArchiveError)


def job_error_answer(exc: Exception) -> ApiError:
    """The answer to a refusal: its status and its sentence."""
    for kind, status in STATUSES:
        if isinstance(exc, kind):
            return ApiError(status, str(exc))
    return ApiError(400, str(exc))


@contextmanager
def answered() -> Iterator[None]:
    """Raise each refusal of the block as its answer."""
    try:
        yield
    except REFUSALS as exc:
        raise job_error_answer(exc) from exc
