"""The one error path of every command: input problems become one line on stderr, never a traceback.

`run_command` wraps a command's body for every entry point (`rangeret`, `python -m service`,
`python -m workers.predict_job`, `python -m workers.train_job`), so users see the same message
shape and exit code whatever they launched. Torch-free, so light commands start quickly.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

from rangeret.dataset.layout import DatasetLayoutError
from rangeret.evaluation.evaluate import EvaluationError
from rangeret.extras import MissingExtraError
from rangeret.io.scans import ScanFormatError
from rangeret.models.weights.hub import WeightsError
from rangeret.submission.archives import SubmissionError

_MAX_DETAILS = 30

#: Exceptions that mean bad input, shown as one line; ValueError covers the library's own input
#: errors (CheckpointError, label-configuration and settings problems) that derive from it.
USER_ERRORS: tuple[type[BaseException], ...] = (
    ScanFormatError,
    DatasetLayoutError,
    EvaluationError,
    SubmissionError,
    WeightsError,
    FileNotFoundError,
    ValueError,
)


class CommandError(Exception):
    """A failure to report to the user as one line, with optional details below it."""

    def __init__(self, reason: str, details: Sequence[str] = ()) -> None:
        super().__init__(reason)
        self.reason = reason
        self.details = list(details)


def run_command(
    program: str, func: Callable[[argparse.Namespace], int], args: argparse.Namespace
) -> int:
    """Run a command's body; input errors become `program: error: reason` (details below it), exit 1.
    A missing extra is its own line (`... needs the EXTRA extra: pip install ...`), exit 1."""
    try:
        return func(args)
    except MissingExtraError as exc:
        print(exc, file=sys.stderr)
        return 1
    except CommandError as exc:
        return fail(program, exc.reason, exc.details)
    except (EvaluationError, SubmissionError) as exc:
        return fail(program, _first_line(exc), exc.problems)
    except USER_ERRORS as exc:
        return fail(program, str(exc))
    except KeyboardInterrupt:
        return fail(program, "interrupted", code=130)


def _first_line(exc: EvaluationError | SubmissionError) -> str:
    n = len(exc.problems)
    return f"{n} problem(s), the first: {exc.problems[0]}" if n else str(exc)


def fail(program: str, reason: str, details: Sequence[str] = (), code: int = 1) -> int:
    """Print `program: error: reason` and up to a screenful of details to stderr; return `code`."""
    print(f"{program}: error: {reason}", file=sys.stderr)
    if len(details) > 1:
        for line in details[:_MAX_DETAILS]:
            print(f"  - {line}", file=sys.stderr)
        if len(details) > _MAX_DETAILS:
            print(f"  ... and {len(details) - _MAX_DETAILS} more", file=sys.stderr)
    return code
