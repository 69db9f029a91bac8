"""`rangeret adapt`: a labelled dataset resampled to another sensor's profile, written in that
profile's layout and point record with `OUT/adapt.json` (`rangeret.adapt`)."""

from __future__ import annotations

import argparse

from rangeret.options import adapt_plan_from_args, add_adapt_options
from rangeret.plugins import Subcommand


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of an adapt run, as the Ray job takes them too (`add_adapt_options`)."""
    add_adapt_options(p)


def run(args: argparse.Namespace) -> int:
    """Adapt every scan of the chosen sequences to the target profile, in this process, and
    print what was adapted."""
    from rangeret.adapt import AdaptStats, adapt_one, finish, summary

    plan = adapt_plan_from_args(args)
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
    print(summary(plan, results, finish(plan, results)))
    return 0


COMMAND = Subcommand(
    "adapt", "resample a labelled dataset to another sensor's profile", add_arguments, run
)
