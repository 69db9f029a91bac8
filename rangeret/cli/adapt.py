"""`rangeret adapt`: a labelled dataset resampled to another sensor's profile, written in that
profile's layout and point record with `OUT/adapt.json` (`rangeret.adapt`)."""

from __future__ import annotations

import argparse

from rangeret.plugins import Subcommand


def add_arguments(p: argparse.ArgumentParser) -> None:
    from rangeret.adapt.runs import add_adapt_arguments

    add_adapt_arguments(p)


def run(args: argparse.Namespace) -> int:
    """Adapt every scan of the chosen sequences to the target profile, in this process."""
    from rangeret.adapt import AdaptStats, adapt_one
    from rangeret.adapt.runs import plan_from_args, report

    plan = plan_from_args(args)
    todo = plan.todo
    results: list[AdaptStats] = []
    bar = None
    if not args.quiet and todo:
        from tqdm import tqdm

        bar = tqdm(total=len(todo), unit="scan", desc="adapting")
    try:
        for job in todo:
            results.append(adapt_one(job, plan.settings))
            if bar is not None:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    return report(plan, results)


COMMAND = Subcommand(
    "adapt", "resample a labelled dataset to another sensor's profile", add_arguments, run
)
