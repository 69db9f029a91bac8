"""`rangeret simulate`: a simulated dataset of street scenes in a profile's layout (folders of
sequences, or a nuScenes version's tables)."""

from __future__ import annotations

import argparse
from pathlib import Path

from rangeret.commands import CommandError
from rangeret.dataset.profiles import DatasetProfile, load_profile
from rangeret.options import add_offset_option, add_profile_option, requested_profile
from rangeret.plugins import Subcommand


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, required=True, metavar="ROOT")
    p.add_argument(
        "--sequences",
        nargs="+",
        metavar="XX:N",
        help="sequences and scan counts (nuScenes: scenes and keyframe counts, such as "
        "scene-0061:3; by default two scenes of each mini split)",
    )
    p.add_argument(
        "--unlabelled", nargs="*", default=[], metavar="XX", help="sequences written without labels"
    )
    p.add_argument("--beams", type=int, help="rows of the sensor (default 64, or the profile's)")
    p.add_argument(
        "--azimuth-steps", type=int, help="columns cast per turn (default 2048, or the profile's)"
    )
    p.add_argument("--seed", type=int, default=0)
    add_offset_option(
        p,
        "render from a sensor moved this far (m: forward, left, up) from its mounting (1.73 m "
        "above the ground, or the profile's sensor.mount_height); the points stay in the "
        "sensor's frame",
    )
    add_profile_option(p)


def run(args: argparse.Namespace) -> int:
    """Write a simulated dataset in a profile's layout, point record and labels."""
    from rangeret.sim import SensorConfig, simulate_dataset

    counts: dict[str, int] = {}
    for item in args.sequences or ():
        name, _, number = item.partition(":")
        if not number.isdigit():
            raise CommandError(f"--sequences takes NAME:SCANS items such as 08:10, got {item!r}")
        counts[name] = int(number)
    profile = requested_profile(args)
    if profile is not None and profile.layout.folders is None:
        return _run_tables(args, profile, counts or None)
    if not counts:
        raise CommandError("--sequences is needed: which sequences, and how many scans each")
    labelled = [s for s in counts if s not in set(args.unlabelled)]
    if profile is None:
        profile = load_profile(None)
        sensor = SensorConfig(
            beams=args.beams or 64,
            azimuth_steps=args.azimuth_steps or 2048,
            offset=tuple(args.sensor_offset),
        )
    else:
        if args.beams is not None and args.beams != profile.projection.height:
            raise CommandError(
                f"--beams {args.beams} contradicts the {profile.name} profile's "
                f"{profile.projection.height} rows; leave --beams out with --profile"
            )
        sensor = SensorConfig.for_profile(
            profile, azimuth_steps=args.azimuth_steps, offset=tuple(args.sensor_offset)
        )
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


def _run_tables(
    args: argparse.Namespace, profile: DatasetProfile, counts: dict[str, int] | None
) -> int:
    """A simulated nuScenes tree (v1.0-mini) with the profile's sensor."""
    from rangeret.sim import SensorConfig
    from rangeret.sim.nuscenes_tree import (
        AZIMUTH_STEPS,
        DEFAULT_SCENES,
        VERSION,
        simulate_nuscenes,
    )

    if args.beams is not None and args.beams != profile.projection.height:
        raise CommandError(
            f"--beams {args.beams} contradicts the {profile.name} profile's "
            f"{profile.projection.height} rows; leave --beams out with --profile"
        )
    scenes = counts or DEFAULT_SCENES
    labelled = [s for s in scenes if s not in set(args.unlabelled)]
    n = simulate_nuscenes(
        args.out,
        scenes,
        labelled=labelled,
        sensor=SensorConfig.for_profile(
            profile,
            azimuth_steps=args.azimuth_steps or AZIMUTH_STEPS,
            offset=tuple(args.sensor_offset),
        ),
        seed=args.seed,
        progress=not args.quiet,
        profile=profile,
    )
    print(
        f"{n} simulated keyframes of {len(scenes)} scenes in {Path(args.out) / VERSION} "
        f"({', '.join(labelled) or 'none'} labelled)"
    )
    return 0


COMMAND = Subcommand("simulate", "write a simulated dataset (street scenes)", add_arguments, run)
