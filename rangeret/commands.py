"""The one error path of every command: a user's error becomes one line on stderr, a bug keeps
its traceback.

`run_command` wraps a command's body for every entry point (`rangeret`, `python -m service`,
`python -m workers.predict_job`, `python -m workers.train_job`), so users see the same message
shape and exit code whatever they launched. Only `RangeRetError` (see `rangeret.exceptions`) is a
user's error; any other exception propagates. Imports nothing but `rangeret.exceptions`, so light
commands start quickly.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

from rangeret.exceptions import CommandError, MissingExtraError, RangeRetError

__all__ = ["CommandError", "fail", "run_command"]

_MAX_DETAILS = 30


def run_command(
    program: str, func: Callable[[argparse.Namespace], int], args: argparse.Namespace
) -> int:
    """Run a command's body; a `RangeRetError` becomes `program: error: reason` (details below
    it) and exit 1, a missing extra its own line (`... needs the EXTRA extra: pip install ...`)
    and exit 1, an interrupt exit 130; anything else is a bug and propagates."""
    try:
        return func(args)
    except MissingExtraError as exc:
        print(exc, file=sys.stderr)
        return 1
    except RangeRetError as exc:
        return fail(program, exc.summary(), exc.detail_lines())
    except KeyboardInterrupt:
        return fail(program, "interrupted", code=130)


def fail(program: str, reason: str, details: Sequence[str] = (), code: int = 1) -> int:
    """Print `program: error: reason` and up to a screenful of details to stderr; return `code`."""
    print(f"{program}: error: {reason}", file=sys.stderr)
    if len(details) > 1:
        for line in details[:_MAX_DETAILS]:
            print(f"  - {line}", file=sys.stderr)
        if len(details) > _MAX_DETAILS:
            print(f"  ... and {len(details) - _MAX_DETAILS} more", file=sys.stderr)
    return code
