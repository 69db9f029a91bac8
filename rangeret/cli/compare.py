"""`rangeret compare`: the per-class IoU of evaluation reports side by side."""

from __future__ import annotations

import argparse
from pathlib import Path

from rangeret.commands import CommandError
from rangeret.plugins import Subcommand


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "reports",
        type=Path,
        nargs="+",
        metavar="REPORT.json",
        help="evaluation reports (of `rangeret evaluate --json`, the Ray job or a gateway job); "
        "the first is the baseline of the deltas",
    )
    p.add_argument(
        "--out", type=Path, metavar="FILE.png", help="also draw the comparison as grouped bars"
    )


def run(args: argparse.Namespace) -> int:
    """Print the per-class IoU of evaluation reports side by side, with deltas against the first."""
    from rangeret.evaluation.compare import compare_reports

    if args.out is not None and args.out.suffix.lower() != ".png":
        raise CommandError(f"--out names the PNG to write, so it must end in .png, got {args.out}")
    comparison = compare_reports(args.reports)
    print(comparison.table())
    if args.out is not None:
        print(f"plot: {comparison.write_png(args.out)}")
    return 0


COMMAND = Subcommand(
    "compare",
    "per-class IoU of evaluation reports side by side, deltas against the first",
    add_arguments,
    run,
)
