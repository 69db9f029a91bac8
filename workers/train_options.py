"""The options of training on Ray, shared by `rangeret train --ray` and `python -m workers.train_job`."""

from __future__ import annotations

import argparse


def add_ray_options(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """--workers: the number of Ray Train workers."""
    parser.add_argument(
        "--workers",
        type=int,
        default=2,
        metavar="N",
        help="Ray Train workers, one GPU each when the cluster has GPUs (default 2)",
    )
