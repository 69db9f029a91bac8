"""The `rangeret` command: predict, evaluate, compare reports, submission archives, training,
simulation, adapting a dataset to another sensor and a speed card of this machine.

This module builds the parser and dispatches; each library subcommand lives in its own module of
`rangeret.cli` (its options and body), and `serve`, `demo` and `train --ray` come from the layers
above it through entry points (`rangeret.plugins`). Each subcommand exits 0 on success and 1 with
a one-line reason (then the details) on a user's error (`rangeret.commands.run_command`); any
other exception is a bug and shows its traceback.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence

from rangeret.cli import (
    adapt,
    bench,
    compare,
    evaluate,
    export,
    predict,
    profile,
    simulate,
    submission,
    view,
    weights,
)
from rangeret.commands import run_command
from rangeret.options import add_output_options
from rangeret.plugins import COMMANDS_GROUP, Subcommand, load_plugins


def _train_arguments(p: argparse.ArgumentParser) -> None:
    """The options of `rangeret train` (`rangeret.cli.train`, imported only for that command)."""
    from rangeret.cli.train import add_train_arguments

    add_train_arguments(p)


def _train(args: argparse.Namespace) -> int:
    """Train a network from a config and the command line (see `rangeret.cli.train`)."""
    from rangeret.cli.train import run_train

    return run_train(args)


#: `rangeret train`; its module needs torch, so it is imported only when the command is used.
TRAIN_COMMAND = Subcommand(
    "train",
    "train a network (in this process, or with --ray on a cluster)",
    _train_arguments,
    _train,
)

#: The library's own subcommands, in the order `rangeret --help` lists them.
BUILTIN_COMMANDS = (
    predict.COMMAND,
    evaluate.COMMAND,
    compare.COMMAND,
    submission.COMMAND,
    submission.VALIDATE_COMMAND,
    view.COMMAND,
    TRAIN_COMMAND,
    simulate.COMMAND,
    adapt.COMMAND,
    profile.COMMAND,
    weights.COMMAND,
    export.COMMAND,
    bench.COMMAND,
)


def subcommands() -> list[Subcommand]:
    """The library's subcommands, then those the installed layers contribute."""
    return [*BUILTIN_COMMANDS, *load_plugins(COMMANDS_GROUP)]


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The argument parser of the `rangeret` command and its subcommands.

    A subcommand's options are added only when `command` names it, or when it is None (every
    option): some need torch or the web stack, and other commands start without them. A
    command whose extra is not installed gets none (`main` refuses it before parsing).
    """
    parser = argparse.ArgumentParser(
        prog="rangeret",
        description="RangeRet LiDAR semantic segmentation: evaluation, submissions and more.",
    )
    common = argparse.ArgumentParser(add_help=False)
    add_output_options(common)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for cmd in subcommands():
        p = sub.add_parser(cmd.name, parents=[common], help=cmd.help)
        if (command is None or command == cmd.name) and cmd.installed():
            cmd.add_arguments(p)
        p.set_defaults(func=cmd.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `rangeret` command."""
    argv = sys.argv[1:] if argv is None else list(argv)
    name = next((a for a in argv if not a.startswith("-")), "")
    command = next((c for c in subcommands() if c.name == name), None)
    if command is not None and not command.installed():
        return run_command(f"rangeret {name}", command.refuse, argparse.Namespace())
    parser = build_parser(name)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
    return run_command(f"rangeret {args.command}", args.func, args)


if __name__ == "__main__":
    sys.exit(main())
