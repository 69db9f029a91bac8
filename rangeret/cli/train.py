"""The `rangeret train` subcommand: its options and what it runs.

`add_train_arguments(parser)` adds the options to an argparse parser and `run_train(args)` runs a
parsed namespace in this process, or on a back-end that a layer above the library contributes as
a `TrainBackend` entry point (the Ray layer adds `--ray`): the library itself never imports Ray.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from rangeret.models import list_models
from rangeret.models.configs import OVERRIDES
from rangeret.options import add_precision_option, add_profile_option, add_projection_options
from rangeret.plugins import TRAIN_BACKENDS_GROUP, TrainBackend, load_plugins
from rangeret.training.config import TrainConfig, profile_reference
from rangeret.training.losses import LOSSES, WEIGHTINGS
from rangeret.training.range_mixes import MIXES
from rangeret.training.schedule import SCHEDULES
from rangeret.training.trainer import BEST, CURVES_PNG, LAST, METRICS_CSV, Trainer


def train_backends() -> list[TrainBackend]:
    """The back-ends the installed layers contribute (group `rangeret.train_backends`)."""
    return load_plugins(TRAIN_BACKENDS_GROUP)


def add_train_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options of `rangeret train` to `parser`: `add_training_options` and those of every
    installed back-end (--ray, --workers)."""
    add_training_options(parser)
    for backend in train_backends():
        backend.add_arguments(parser)


def add_training_options(parser: argparse.ArgumentParser) -> None:
    """The options that define a training run (everything but where it runs)."""
    defaults = TrainConfig(dataset="", out="")
    data = parser.add_argument_group("data")
    data.add_argument(
        "--dataset",
        type=Path,
        required=True,
        metavar="ROOT",
        help="dataset tree in the profile's layout (SemanticKITTI: ROOT/sequences/XX/{velodyne,labels})",
    )
    add_profile_option(data)
    data.add_argument(
        "--train-sequences",
        nargs="+",
        metavar="XX",
        help="training sequences (default: the profile's train split)",
    )
    data.add_argument(
        "--val-sequences",
        nargs="*",
        metavar="XX",
        help="validation sequences (default: the valid split); give none to skip validation",
    )
    data.add_argument(
        "--label-config",
        type=Path,
        metavar="FILE",
        help="label configuration (.json of this project or an official .yaml) in place of the "
        "profile's",
    )
    add_projection_options(data)
    data.add_argument(
        "--no-augment",
        action="store_true",
        help="no point augmentation (scale, rotation, shift, flip)",
    )
    data.add_argument(
        "--mixes",
        nargs="+",
        choices=MIXES,
        default=[],
        metavar="MIX",
        help=f"RangeFormer's range-image mixes to apply ({', '.join(MIXES)})",
    )
    data.add_argument(
        "--mix-probability",
        type=float,
        default=defaults.mix_probability,
        metavar="P",
        help="probability of each chosen mix per sample (default 0.5)",
    )
    data.add_argument(
        "--loader-workers",
        type=int,
        default=defaults.loader_workers,
        metavar="N",
        help="data-loading processes per trainer (default 2; 0 loads in the training process)",
    )

    net = parser.add_argument_group("network")
    net.add_argument("--model", required=True, choices=list_models(), help="network to train")
    net.add_argument(
        "--override",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help=f"ablation switch of the network ({', '.join(OVERRIDES)}), e.g. decay=manhattan; repeatable",
    )

    opt = parser.add_argument_group("optimisation")
    opt.add_argument("--epochs", type=int, default=defaults.epochs, metavar="N", help="default 64")
    opt.add_argument(
        "--max-steps",
        type=int,
        metavar="N",
        help="stop after N steps; the schedule then spans min(epochs x steps per epoch, N)",
    )
    opt.add_argument(
        "--batch-size",
        type=int,
        default=defaults.batch_size,
        metavar="N",
        help="scans per step and per trainer (default 1, as in the thesis)",
    )
    opt.add_argument(
        "--lr",
        type=float,
        default=defaults.lr,
        help="AdamW learning rate, where the schedule starts (default 1e-3)",
    )
    opt.add_argument(
        "--max-lr", type=float, default=defaults.max_lr, help="peak of the schedule (default 1e-2)"
    )
    opt.add_argument(
        "--weight-decay",
        type=float,
        default=defaults.weight_decay,
        help="AdamW weight decay (default 0.05)",
    )
    opt.add_argument(
        "--schedule",
        choices=SCHEDULES,
        default=defaults.schedule,
        help="onecycle (the thesis's) or linear warm-up + cosine",
    )
    opt.add_argument(
        "--warmup",
        type=float,
        default=defaults.warmup,
        metavar="SHARE",
        help="share of the steps spent warming up (default 0.3; chapter 5 used 0.02)",
    )
    opt.add_argument(
        "--loss",
        nargs="+",
        choices=LOSSES,
        default=list(LOSSES),
        dest="losses",
        help="losses to sum with equal weights (default: all three)",
    )
    opt.add_argument(
        "--class-weights",
        choices=WEIGHTINGS,
        default=defaults.class_weighting,
        help="cross-entropy class weights from class frequencies (default 1/sqrt(f + 1e-3))",
    )
    opt.add_argument("--focal-gamma", type=float, default=defaults.focal_gamma, help="default 2")
    opt.add_argument(
        "--clip-grad",
        type=float,
        default=defaults.clip_grad,
        metavar="NORM",
        help="clip the gradient norm (default 1; 0 turns clipping off)",
    )
    add_precision_option(opt)
    opt.add_argument(
        "--no-amp",
        action="store_true",
        help="the same as --precision fp32 (no mixed precision), kept for older command lines",
    )
    opt.add_argument(
        "--seed",
        type=int,
        default=defaults.seed,
        help="seed of initialisation, order and augmentation",
    )

    run = parser.add_argument_group("run")
    run.add_argument(
        "--out",
        type=Path,
        required=True,
        metavar="DIR",
        help="writes last.pt, best.pt, last.state.pt, metrics.csv, steps.csv, curves.png",
    )
    run.add_argument("--resume", action="store_true", help="continue the run saved in DIR exactly")
    run.add_argument(
        "--checkpoint-every",
        type=int,
        default=0,
        metavar="N",
        help="also save last.pt and the state every N steps (default: at epoch ends)",
    )
    run.add_argument(
        "--device",
        default="auto",
        choices=["auto", "cpu", "cuda"],
        help="auto picks CUDA when present (default)",
    )


def parse_override(text: str) -> tuple[str, Any]:
    """'name=value' as (name, value): ints, booleans and 'AxB' pairs are converted."""
    name, sep, value = text.partition("=")
    name = name.strip().replace("-", "_")
    if not sep or name not in OVERRIDES:
        raise ValueError(
            f"--override takes NAME=VALUE with NAME one of {', '.join(OVERRIDES)}, got {text!r}"
        )
    value = value.strip()
    if value.lower() in ("true", "false"):
        return name, value.lower() == "true"
    if value.isdigit():
        return name, int(value)
    parts = value.lower().replace(",", "x").split("x")
    if len(parts) == 2 and all(p.isdigit() for p in parts):
        return name, (int(parts[0]), int(parts[1]))
    return name, value


def precision_from_args(args: argparse.Namespace) -> str:
    """--precision, with --no-amp read as fp32; a --precision that contradicts --no-amp is a
    ValueError naming both."""
    if not args.no_amp:
        return args.precision
    if args.precision not in ("auto", "fp32"):
        raise ValueError(
            f"--no-amp means --precision fp32 and contradicts --precision {args.precision}: "
            "give one of them"
        )
    return "fp32"


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    """The `TrainConfig` of parsed `rangeret train` options (ValueError on invalid values); paths
    are made absolute, so that workers in other folders and resumed runs read the same ones."""
    return TrainConfig(
        dataset=str(Path(args.dataset).resolve()),
        out=str(Path(args.out).resolve()),
        model=args.model,
        profile=profile_reference(getattr(args, "profile", None)),
        height=args.height,
        width=args.width,
        fov_up=args.fov_up,
        fov_down=args.fov_down,
        label_config=str(Path(args.label_config).resolve()) if args.label_config else None,
        train_sequences=tuple(args.train_sequences) if args.train_sequences else None,
        val_sequences=tuple(args.val_sequences) if args.val_sequences is not None else None,
        model_overrides=tuple(parse_override(o) for o in args.override),
        epochs=args.epochs,
        max_steps=args.max_steps,
        batch_size=args.batch_size,
        lr=args.lr,
        max_lr=args.max_lr,
        weight_decay=args.weight_decay,
        schedule=args.schedule,
        warmup=args.warmup,
        losses=tuple(args.losses),
        class_weighting=args.class_weights,
        focal_gamma=args.focal_gamma,
        clip_grad=args.clip_grad,
        precision=precision_from_args(args),
        augment=not args.no_augment,
        mixes=tuple(args.mixes),
        mix_probability=args.mix_probability,
        seed=args.seed,
        device=args.device,
        loader_workers=args.loader_workers,
        checkpoint_every=args.checkpoint_every,
        resume=args.resume,
        progress=not getattr(args, "quiet", False),
    )


def run_train(args: argparse.Namespace) -> int:
    """Run `rangeret train` for parsed options; returns 0, raises ValueError (or a subclass such
    as DatasetLayoutError, or MissingExtraError for a back-end whose extra is not installed) or
    FileNotFoundError with a one-line reason on bad input."""
    from rangeret.models import load_checkpoint

    config = config_from_args(args)
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
