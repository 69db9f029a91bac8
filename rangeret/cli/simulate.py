"""`rangeret simulate`: a simulated dataset of street scenes in a profile's layout."""

from __future__ import annotations

import argparse
from pathlib import Path

from rangeret.commands import CommandError
from rangeret.dataset.profiles import load_profile
from rangeret.options import add_profile_option, requested_profile
from rangeret.plugins import Subcommand


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, required=True, metavar="ROOT")
    p.add_argument(
        "--sequences", nargs="+", required=True, metavar="XX:N", help="sequences and scan counts"
    )
    p.add_argument(
        "--unlabelled", nargs="*", default=[], metavar="XX", help="sequences written without labels"
    )
    p.add_argument("--beams", type=int, help="rows of the sensor (default 64, or the profile's)")
    p.add_argument(
        "--azimuth-steps", type=int, help="columns cast per turn (default 2048, or the profile's)"
    )
    p.add_argument("--seed", type=int, default=0)
    add_profile_option(p)


def run(args: argparse.Namespace) -> int:
    """Write a simulated dataset in a profile's layout, point record and labels."""
    from rangeret.sim import SensorConfig, simulate_dataset

    counts: dict[str, int] = {}
    for item in args.sequences:
        name, _, number = item.partition(":")
        if not number.isdigit():
            raise CommandError(f"--sequences takes NAME:SCANS items such as 08:10, got {item!r}")
        counts[name] = int(number)
    labelled = [s for s in counts if s not in set(args.unlabelled)]
    profile = requested_profile(args)
    if profile is None:
        profile = load_profile(None)
        sensor = SensorConfig(beams=args.beams or 64, azimuth_steps=args.azimuth_steps or 2048)
    else:
        if args.beams is not None and args.beams != profile.projection.height:
            raise CommandError(
                f"--beams {args.beams} contradicts the {profile.name} profile's "
                f"{profile.projection.height} rows; leave --beams out with --profile"
            )
        sensor = SensorConfig.for_profile(profile, azimuth_steps=args.azimuth_steps)
    n = simulate_dataset(
        args.out,
        counts,
        labelled=labelled,
        sensor=sensor,
        seed=args.seed,
        progress=not args.quiet,
        profile=profile,
    )
    print(f"{n} simulated scans in {args.out} ({', '.join(labelled) or 'none'} labelled)")
    return 0


COMMAND = Subcommand("simulate", "write a simulated dataset (street scenes)", add_arguments, run)
