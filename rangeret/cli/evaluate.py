"""`rangeret evaluate`: per-class IoU of a predictions tree against ground truth, or with
`--panoptic` the panoptic quality of its objects as the profile's panoptic benchmark scores it."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import TYPE_CHECKING

from rangeret.commands import CommandError
from rangeret.options import (
    add_label_config,
    add_profile_option,
    add_selection,
    profile_from_args,
    selected_dataset,
)
from rangeret.plugins import Subcommand

if TYPE_CHECKING:
    from rangeret.dataset.profiles import DatasetProfile
    from rangeret.dataset.selection import DatasetSelection

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
    p.add_argument(
        "--panoptic",
        action="store_true",
        help="score panoptic predictions (`predict --panoptic`) against the panoptic ground "
        "truth: PQ, SQ, RQ, PQ-dagger and IoU as the profile's panoptic benchmark computes them",
    )
    p.add_argument(
        "--min-points",
        type=int,
        metavar="N",
        help="with --panoptic: unmatched objects of fewer points count as neither false "
        "positives nor false negatives (default: the benchmark's, 50 for SemanticKITTI and 15 "
        "for nuScenes-panoptic)",
    )
    add_profile_option(p)
    add_label_config(p)


def run(args: argparse.Namespace) -> int:
    """Evaluate a predictions tree against ground truth with the official semantics."""
    from rangeret.evaluation.evaluate import evaluate_predictions

    profile = profile_from_args(args)
    if args.min_points is not None and not args.panoptic:
        raise CommandError("--min-points is an option of --panoptic evaluation")
    if args.min_points is not None and args.min_points < 1:
        raise CommandError(f"--min-points must be at least 1, got {args.min_points}")
    selection = selected_dataset(args, profile, args.dataset, doing="evaluating")
    if args.panoptic:
        return _run_panoptic(args, profile, selection)
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


def _run_panoptic(
    args: argparse.Namespace, profile: DatasetProfile, selection: DatasetSelection
) -> int:
    """Score panoptic predictions under the profile's panoptic benchmark's rules."""
    from rangeret.evaluation.panoptic_evaluate import evaluate_panoptic
    from rangeret.io.run_info import read_run_info
    from rangeret.submission.benchmarks import benchmark_of

    if profile.panoptic_refusal() is not None:
        raise CommandError(str(profile.panoptic_refusal()))
    benchmark = benchmark_of(profile, panoptic=True)
    if benchmark.panoptic_rules is None:
        raise CommandError(
            f"the {profile.name} profile has no panoptic benchmark to score by (its "
            "`benchmark.panoptic` names none)"
        )
    if args.plots:
        raise CommandError("--plots draws the semantic report; leave it out with --panoptic")
    report = evaluate_panoptic(
        selection,
        args.predictions,
        profile=profile,
        rules=benchmark.panoptic_rules,
        benchmark=benchmark.name,
        min_points=args.min_points,
        checkpoint_sha256=read_run_info(args.predictions).get("checkpoint_sha256"),
        progress=not args.quiet,
    )
    print(report.table())
    if args.json:
        report.write_json(args.json)
        print(f"report: {args.json}")
    return 0


COMMAND = Subcommand(
    "evaluate", "per-class IoU of predictions against ground truth", add_arguments, run
)
