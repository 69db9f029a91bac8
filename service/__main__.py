"""`python -m service`: the gateway without the `rangeret` command (same options as `rangeret serve`)."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence

from rangeret.commands import run_command
from rangeret.exceptions import MissingExtraError
from rangeret.extras import extra_installed


def main(argv: Sequence[str] | None = None) -> int:
    """Parse the options and serve; bad input, or a missing gateway extra, becomes a one-line
    message and exit code 1."""
    if not extra_installed("gateway"):
        print(MissingExtraError("python -m service", "gateway"), file=sys.stderr)
        return 1
    from service.server import add_serve_arguments, run_serve

    parser = argparse.ArgumentParser(
        prog="python -m service", description="The RangeRet HTTP gateway."
    )
    add_serve_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    return run_command("serve", run_serve, args)


if __name__ == "__main__":
    sys.exit(main())
