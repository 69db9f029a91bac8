"""`python -m service`: the gateway without the `rangeret` command (same options as `rangeret serve`)."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence

from rangeret.commands import run_command
from service.server import add_serve_arguments, run_serve


def main(argv: Sequence[str] | None = None) -> int:
    """Parse the options and serve; bad input becomes a one-line message and exit code 1."""
    parser = argparse.ArgumentParser(
        prog="python -m service", description="The RangeRet HTTP gateway."
    )
    add_serve_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    return run_command("serve", run_serve, args)


if __name__ == "__main__":
    sys.exit(main())
