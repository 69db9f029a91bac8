"""What the gateway adds to the `rangeret` command: `rangeret serve`.

Declared as an entry point in `pyproject.toml` and loaded by `rangeret.plugins`. This module
imports neither the web stack nor torch: the options and the body import them when used, and
without the gateway extra `rangeret serve` stops with the one line naming it.
"""

from __future__ import annotations

import argparse

from rangeret.plugins import Subcommand


def _serve_arguments(parser: argparse.ArgumentParser) -> None:
    from service.server import add_serve_arguments

    add_serve_arguments(parser)


def _serve(args: argparse.Namespace) -> int:
    from service.server import run_serve

    return run_serve(args)


SERVE = Subcommand(
    "serve", "the HTTP gateway (FastAPI on uvicorn)", _serve_arguments, _serve, extra="gateway"
)
