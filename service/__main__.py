"""`python -m service`: the gateway without the `rangeret` command (same options as `rangeret serve`)."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence

from rangeret.cli import CommandError
from service.server import add_serve_arguments, run_serve


def main(argv: Sequence[str] | None = None) -> int:
    """Parse the options, serve, and turn bad input into a one-line message and exit code 1."""
    parser = argparse.ArgumentParser(prog="python -m service", description="The RangeRet HTTP gateway.")
    add_serve_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        return run_serve(args)
    except CommandError as exc:
        print(f"serve: error: {exc.reason}", file=sys.stderr)
        return 1
    except (ValueError, FileNotFoundError) as exc:
        print(f"serve: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
