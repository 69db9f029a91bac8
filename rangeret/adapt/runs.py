"""What every driver of an adapt run shares (the `rangeret adapt` command, the Ray job): its
options, the plan its parsed options ask for, and the report it prints at the end."""

from __future__ import annotations

import argparse
from pathlib import Path

from rangeret.adapt.resample import AdaptStats, check_offset, check_profiles, unmeasured_beams
from rangeret.adapt.tree import AdaptPlan, AdaptSettings, finish, plan_adaptation
from rangeret.commands import CommandError
from rangeret.dataset.label_map import load_label_map
from rangeret.dataset.profiles import load_profile
from rangeret.options import add_offset_option, add_selection, selected_sequences


def add_adapt_arguments(p: argparse.ArgumentParser) -> None:
    """The options of an adapt run: dataset, profiles, output, selection, offset, map."""
    p.add_argument(
        "--dataset", type=Path, required=True, metavar="ROOT", help="the labelled source dataset"
    )
    p.add_argument(
        "--profile",
        required=True,
        metavar="SOURCE",
        help="the source dataset's profile: a built-in name or a YAML file",
    )
    p.add_argument(
        "--to-profile",
        required=True,
        metavar="TARGET",
        help="the target sensor's profile (its beams, image, range, reflectance scale, record, "
        "labels and layout): a built-in name or a YAML file",
    )
    p.add_argument(
        "--out",
        type=Path,
        required=True,
        metavar="OUT",
        help="the adapted dataset's root, outside ROOT (and not holding it)",
    )
    add_selection(p)
    add_offset_option(
        p,
        "where the target sensor sits in the source sensor's frame (m: forward, left, up; "
        "default 0 0 0): every point moves by minus this offset",
    )
    p.add_argument(
        "--label-map",
        type=Path,
        metavar="MAP.yaml",
        help="a YAML mapping `source raw id: target raw id` (many to one); without it raw ids "
        "are kept and must be the target profile's",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="adapt every chosen scan again and replace its outputs, also where OUT/adapt.json "
        "records other settings (without it, scans already adapted with these settings are "
        "kept); the dataset itself is never written",
    )


def plan_from_args(args: argparse.Namespace) -> AdaptPlan:
    """The run the parsed options ask for: profiles, offset and label map checked, scans listed
    and `OUT/adapt.json` begun (`plan_adaptation`); every driver of `adapt` starts here."""
    if args.version is not None:
        raise CommandError("--version is for a dataset of tables; adapt reads folders of sequences")
    source, target = load_profile(args.profile), load_profile(args.to_profile)
    check_profiles(source, target)
    settings = AdaptSettings(
        source,
        target,
        check_offset(args.sensor_offset),
        None if args.label_map is None else load_label_map(args.label_map, target),
    )
    sequences = selected_sequences(args, source, args.dataset, doing="adapting")
    return plan_adaptation(args.dataset, args.out, sequences, settings, overwrite=args.overwrite)


def report(plan: AdaptPlan, results: list[AdaptStats]) -> int:
    """Finish the run's record (`finish`) and print what was adapted, dropped and left empty;
    every driver of `adapt` ends here. Returns the exit code, 0."""
    info = finish(plan, results)
    total = sum(results, AdaptStats())
    skipped = f" ({plan.skipped} already there)" if plan.skipped else ""
    print(f"scans adapted into {plan.out}: {total.scans}{skipped}")
    if total.scans:
        print(
            f"points: {total.points_kept:,} of {total.points_in:,} kept; dropped "
            f"{total.dropped_fov:,} outside the field of view, {total.dropped_range:,} out of "
            f"range, {total.dropped_collisions:,} on a pixel another point won"
        )
    if total.empty_scans:
        print(f"{total.empty_scans} scan(s) kept no point and were left out")
    source, target = plan.settings.source, plan.settings.target
    beams = unmeasured_beams(source, target)
    if beams:
        print(
            f"{len(beams)} beam(s) of {target.name} lie outside the source's field of view and "
            f"stay empty: {', '.join(map(str, beams))}"
        )
    print(f"record: {info}")
    return 0
