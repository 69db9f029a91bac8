"""`rangeret evaluate`: per-class IoU of a predictions tree against ground truth."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from rangeret.options import (
    add_label_config,
    add_profile_option,
    add_selection,
    profile_from_args,
    selected_dataset,
)
from rangeret.plugins import Subcommand

log = logging.getLogger("rangeret")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dataset", type=Path, required=True, metavar="ROOT")
    p.add_argument("--predictions", type=Path, required=True, metavar="PRED")
    add_selection(p)
    p.add_argument("--json", type=Path, metavar="FILE", help="write the JSON report here")
    p.add_argument(
        "--plots",
        type=Path,
        metavar="DIR",
        help="write confusion.png, iou.png, iou-by-distance.png and miou-by-sequence.png here",
    )
    add_profile_option(p)
    add_label_config(p)


def run(args: argparse.Namespace) -> int:
    """Evaluate a predictions tree against ground truth with the official semantics."""
    from rangeret.evaluation.evaluate import evaluate_predictions

    profile = profile_from_args(args)
    selection = selected_dataset(args, profile, args.dataset, doing="evaluating")
    report = evaluate_predictions(
        selection, args.predictions, progress=not args.quiet, profile=profile
    )
    print(report.table())
    for note in report.notes:
        log.warning(note)
    if args.json:
        report.write_json(args.json)
        print(f"report: {args.json}")
    if args.plots:
        from rangeret.evaluation.plots import write_plots

        for path in write_plots(report, args.plots, config=profile.labels):
            print(f"plot: {path}")
    return 0


COMMAND = Subcommand(
    "evaluate", "per-class IoU of predictions against ground truth", add_arguments, run
)
