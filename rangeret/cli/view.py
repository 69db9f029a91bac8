"""`rangeret view`: a scan with its labels as a coloured PLY point cloud and a bird's-eye PNG."""

from __future__ import annotations

import argparse
from pathlib import Path

from rangeret.commands import CommandError
from rangeret.io.point_fields import parse_field_overrides
from rangeret.options import (
    add_decoded_limit_option,
    add_field_option,
    add_profile_option,
    decode_limits_from_args,
    profile_from_args,
)
from rangeret.plugins import Subcommand


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "scan",
        type=Path,
        metavar="SCAN",
        help="a point-cloud file: .bin (the profile's record), .pcd, .ply, .las or .laz",
    )
    p.add_argument(
        "--labels", type=Path, metavar="FILE", help="predicted .label file (colours the cloud)"
    )
    p.add_argument(
        "--ground-truth",
        type=Path,
        metavar="FILE",
        help="ground-truth .label file (colours the cloud without --labels; with it, an error map)",
    )
    p.add_argument(
        "--out",
        type=Path,
        required=True,
        metavar="FILE.ply|FILE.png",
        help="a binary PLY (x, y, z, red, green, blue, label) with a bird's-eye PNG of the same "
        "stem beside it, or the PNG alone",
    )
    add_profile_option(p)
    add_field_option(p)
    add_decoded_limit_option(p)


def run(args: argparse.Namespace) -> int:
    """Write a scan with its labels as a coloured PLY point cloud and a bird's-eye PNG."""
    from rangeret.evaluation.view import load_labelled_scan, write_view

    if args.out.suffix not in (".ply", ".png"):
        raise CommandError(
            f"--out {args.out}: the file must end with .ply (point cloud and PNG) or .png (PNG only)"
        )
    profile = profile_from_args(args)
    overrides = parse_field_overrides(args.field, record=profile.points)
    view = load_labelled_scan(
        args.scan,
        args.labels,
        args.ground_truth,
        profile=profile,
        overrides=overrides,
        limits=decode_limits_from_args(args),
    )
    for path in write_view(view, args.out, profile):
        print(f"{path.suffix[1:]}: {path}")
    left_out = f" ({view.invalid_points:,} invalid points left out)" if view.invalid_points else ""
    print(f"{len(view.points):,} points of {args.scan}{left_out}, coloured by {view.coloured_by}")
    return 0


COMMAND = Subcommand(
    "view",
    "a scan with its labels as a coloured PLY point cloud and bird's-eye PNGs",
    add_arguments,
    run,
)
