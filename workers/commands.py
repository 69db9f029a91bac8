"""What the Ray layer adds to the `rangeret` command: `rangeret demo` and `rangeret train --ray`.

Declared as entry points in `pyproject.toml` and loaded by `rangeret.plugins`. This module
imports neither torch nor Ray: the bodies import them when they run, and without the ray extra
both stop with the one line naming it.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from rangeret.options import (
    add_leaderboard_options,
    add_precision_option,
    add_profile_option,
    leaderboard_from_args,
    requested_profile,
)
from rangeret.plugins import Subcommand, TrainBackend
from workers.train_options import add_ray_options

if TYPE_CHECKING:
    from rangeret.training.config import TrainConfig


def _demo_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--out", type=Path, metavar="DIR", help="results folder (default: a new one)"
    )
    parser.add_argument(
        "--checkpoint",
        type=Path,
        metavar="FILE",
        help="other weights (default: the bundled demo weights)",
    )
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="run into an --out whose predictions are another checkpoint's (the demo predicts "
        "every scan again; predictions/run.json lists both runs)",
    )
    parser.add_argument(
        "--panoptic",
        action="store_true",
        help="find the objects too: panoptic labels predicted on Ray, scored as the profile's "
        "panoptic benchmark scores them (PQ beside mIoU) and archived for it",
    )
    add_profile_option(parser)
    add_precision_option(parser)
    add_leaderboard_options(
        parser.add_argument_group("leaderboard (description.txt of the archive)")
    )


def _run_demo(args: argparse.Namespace) -> int:
    from workers.demo import run_demo

    leaderboard = leaderboard_from_args(args)
    run_demo(
        args.out,
        checkpoint=args.checkpoint,
        progress=not args.quiet,
        profile=requested_profile(args),
        precision=args.precision,
        leaderboard=leaderboard,
        overwrite=args.overwrite,
        panoptic=args.panoptic,
    )
    return 0


DEMO = Subcommand(
    "demo", "the whole pipeline on a small simulated example", _demo_arguments, _run_demo, "ray"
)


def _ray_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("ray")
    group.add_argument(
        "--ray",
        action="store_true",
        help="data-parallel on the Ray cluster of RAY_ADDRESS (or a local one) with Ray Train",
    )
    add_ray_options(group)


def _train_on_ray(config: TrainConfig, args: argparse.Namespace) -> None:
    from rangeret.training.config import TrainConfigError
    from workers.train_job import run_ray

    if args.workers < 1:
        raise TrainConfigError(f"--workers must be at least 1, got {args.workers}")
    run_ray(config, workers=args.workers)


RAY_TRAINING = TrainBackend(
    add_arguments=_ray_arguments,
    selected=lambda args: bool(getattr(args, "ray", False)),
    run=_train_on_ray,
    option="--ray",
    extra="ray",
)
