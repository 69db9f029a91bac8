"""The `rangeret train` subcommand: its options and what it runs.

`add_train_arguments(parser)` adds the options (`rangeret.train_options`: one per `TrainConfig`
field, `--config FILE.yaml` and `--print-config`) to an argparse parser and `run_train(args)`
runs a parsed namespace in this process, or on a back-end that a layer above the library
contributes as a `TrainBackend` entry point (the Ray layer adds `--ray`): the library itself
never imports Ray.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from rangeret.plugins import TRAIN_BACKENDS_GROUP, TrainBackend, load_plugins
from rangeret.train_options import add_training_options, config_from_args
from rangeret.training.config_file import config_yaml
from rangeret.training.state import BEST, CURVES_PNG, LAST, METRICS_CSV
from rangeret.training.trainer import Trainer


def train_backends() -> list[TrainBackend]:
    """The back-ends the installed layers contribute (group `rangeret.train_backends`)."""
    return load_plugins(TRAIN_BACKENDS_GROUP)


def add_train_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options of `rangeret train` to `parser`: `add_training_options` and those of every
    installed back-end (--ray, --workers)."""
    add_training_options(parser)
    for backend in train_backends():
        backend.add_arguments(parser)


def run_train(args: argparse.Namespace) -> int:
    """Run `rangeret train` for parsed options (or print their settings with --print-config);
    returns 0, raises a `RangeRetError` (such as DatasetLayoutError, TrainConfigError, or
    MissingExtraError for a back-end whose extra is not installed) or
    FileNotFoundError with a one-line reason on bad input."""
    from rangeret.models import load_checkpoint

    config = config_from_args(args)
    if args.print_config:
        print(config_yaml(config), end="")
        return 0
    backend = next((b for b in train_backends() if b.selected(args)), None)
    if backend is not None:
        backend.check()
        backend.run(config, args)
    else:
        Trainer(config).fit()
    out = Path(config.out)
    best = load_checkpoint(out / BEST).checkpoint_info.metadata or {}
    record = best.get("best") or {}
    print(f"last checkpoint: {out / LAST}")
    if record:
        print(
            f"best checkpoint: {out / BEST} (epoch {record['epoch']}, {record['metric']} {record['value']:.4f})"
        )
    print(f"metrics: {out / METRICS_CSV}; curves: {out / CURVES_PNG}")
    return 0
