"""`rangeret profile`: list the built-in dataset profiles, show one as YAML, or measure a sensor's
input normalisation on its data."""

from __future__ import annotations

import argparse
from pathlib import Path

from rangeret.dataset.profiles import builtin_profiles, load_profile
from rangeret.options import add_selection, selected_sequences
from rangeret.plugins import Subcommand


def add_arguments(p: argparse.ArgumentParser) -> None:
    actions = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    actions.add_parser("list", help="the built-in profiles")
    show = actions.add_parser("show", help="a profile as YAML (a file to start a new one from)")
    show.add_argument("name", metavar="NAME|FILE")
    stats = actions.add_parser(
        "stats",
        help="a sensor's channel means/stds and projection checks, measured on its scans",
        description="Means and stds of the five input channels over the range images' filled "
        "pixels (raw values of each pixel's winning point), points per scan, the share that win "
        "a pixel, and the laser ids or the points outside the vertical field of view.",
    )
    stats.add_argument("--dataset", type=Path, required=True, metavar="ROOT")
    stats.add_argument(
        "--profile",
        required=True,
        metavar="NAME|FILE",
        help="the profile whose projection, layout and point record the scans are read with",
    )
    add_selection(stats)
    stats.add_argument(
        "--max-scans",
        type=int,
        metavar="N",
        help="at most N scans, spread evenly over the selection (default: every scan)",
    )
    stats.add_argument("--json", type=Path, metavar="FILE", help="write the numbers here as JSON")
    # -q and -v after the action too; left out there, the values given before it stand.
    stats.add_argument(
        "-q", "--quiet", action="store_true", default=argparse.SUPPRESS, help="no progress bars"
    )
    stats.add_argument(
        "-v", "--verbose", action="store_true", default=argparse.SUPPRESS, help="debug logging"
    )


def run(args: argparse.Namespace) -> int:
    """List the built-in dataset profiles, print one as the YAML that --profile FILE takes, or
    measure a sensor's input normalisation on its data."""
    if args.action == "list":
        for name in builtin_profiles():
            profile = load_profile(name)
            p = profile.projection
            print(
                f"{name:15s} {p.height} x {p.width}, {profile.num_classes} classes, "
                f"{profile.points.num_fields} floats per point, rows from {p.row}"
            )
        return 0
    if args.action == "stats":
        from rangeret.dataset.profile_stats import profile_stats

        profile = load_profile(args.profile)
        stats = profile_stats(
            args.dataset,
            selected_sequences(args, profile, args.dataset, doing="measuring"),
            profile,
            max_scans=args.max_scans,
            progress=not args.quiet,
        )
        print(stats.text())
        if args.json:
            import json

            from rangeret.io.atomic import atomic_write_text

            atomic_write_text(args.json, json.dumps(stats.to_dict(), indent=2) + "\n")
            print(f"stats: {args.json}")
        return 0
    print(load_profile(args.name).to_yaml(), end="")
    return 0


COMMAND = Subcommand(
    "profile", "dataset profiles: list the built-in ones, show one as YAML", add_arguments, run
)
