"""The `rangeret` command: evaluation, submission archives and the example run.

Each subcommand exits 0 on success and 1 with a one-line reason (then the details) on any
problem with its input; it never shows a traceback for bad input.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from rangeret.evaluation import EvaluationError
from rangeret.io import ScanFormatError
from rangeret.labels import LabelConfig, load_label_config
from rangeret.layout import DatasetLayoutError, resolve_sequences
from rangeret.submission import SubmissionError

log = logging.getLogger("rangeret")

_MAX_DETAILS = 30


class CommandError(Exception):
    """A failure to report to the user as one line, with optional details below it."""

    def __init__(self, reason: str, details: Sequence[str] = ()) -> None:
        super().__init__(reason)
        self.reason = reason
        self.details = list(details)


def add_selection(parser: argparse.ArgumentParser, splits: Sequence[str]) -> None:
    """--split or --sequences, exactly one of them."""
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument(
        "--split", choices=list(splits), help="an official split of the label configuration"
    )
    group.add_argument(
        "--sequences",
        nargs="+",
        metavar="XX",
        help="sequence folder names (also data outside the official splits)",
    )


def _add_label_config(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--label-config",
        type=Path,
        metavar="FILE",
        help="label configuration (.json of this project or an official semantic-kitti .yaml); "
        "default: the bundled SemanticKITTI one",
    )


def _label_config(args: argparse.Namespace) -> LabelConfig:
    try:
        return load_label_config(args.label_config)
    except (OSError, ValueError, KeyError) as exc:
        raise CommandError(
            f"cannot read the label configuration {args.label_config}: {exc}"
        ) from exc


def selected_sequences(args: argparse.Namespace, config: LabelConfig) -> list[str]:
    """The sequences chosen by --split or --sequences."""
    return resolve_sequences(split=args.split, sequences=args.sequences, config=config)


def add_network_options(parser: argparse.ArgumentParser) -> None:
    """The options shared by every command that runs a network (predict, serve, the Ray job)."""
    g = parser.add_argument_group("network")
    g.add_argument(
        "--model",
        choices=["rangeret-thesis", "rangeret-cir"],
        help="network name; recognised from the checkpoint when omitted",
    )
    g.add_argument(
        "--checkpoint",
        type=Path,
        metavar="FILE",
        help="weights: the project's own checkpoint or a published .pt file "
        "(default: the bundled demo weights, trained on simulated scenes only)",
    )
    g.add_argument("--height", type=int, help="range image rows (published files: default 64)")
    g.add_argument("--width", type=int, help="range image columns (published files: default 1024)")
    g.add_argument(
        "--fov-up", type=float, metavar="DEG", help="upper vertical field of view (default 3)"
    )
    g.add_argument(
        "--fov-down", type=float, metavar="DEG", help="lower vertical field of view (default -25)"
    )
    g.add_argument(
        "--batch-size", type=int, default=1, metavar="N", help="scans per network pass (default 1)"
    )
    g.add_argument(
        "--no-knn",
        action="store_true",
        help="take each point's pixel class, without kNN refinement",
    )
    g.add_argument(
        "--device",
        default="auto",
        choices=["auto", "cpu", "cuda"],
        help="auto picks CUDA when present (default)",
    )
    g.add_argument(
        "--tta-flip", action="store_true", help="test-time augmentation: add the mirrored view"
    )
    g.add_argument(
        "--tta-shifts",
        type=int,
        default=0,
        metavar="N",
        help="test-time augmentation: add N azimuth-rotated views",
    )


def spec_from_args(args: argparse.Namespace):
    """A `PredictorSpec` from the shared network options (checked, not loaded yet)."""
    from rangeret.inference import KnnSettings, PredictorSpec, TtaSettings, resolve_checkpoint

    if args.batch_size < 1:
        raise CommandError(f"--batch-size must be at least 1, got {args.batch_size}")
    if args.tta_shifts < 0:
        raise CommandError(f"--tta-shifts must not be negative, got {args.tta_shifts}")
    tta = (
        TtaSettings(flip=args.tta_flip, shifts=args.tta_shifts)
        if (args.tta_flip or args.tta_shifts)
        else None
    )
    return PredictorSpec(
        checkpoint=str(resolve_checkpoint(args.checkpoint)),
        model=args.model,
        height=args.height,
        width=args.width,
        fov_up=args.fov_up,
        fov_down=args.fov_down,
        device=args.device,
        knn=None if args.no_knn else KnnSettings(),
        tta=tta,
    )


def predictor_from_args(args: argparse.Namespace):
    """A loaded `Predictor` from the shared network options, announced in the log."""
    predictor = spec_from_args(args).build()
    info = predictor.describe()
    log.info(
        "%s from %s (sha256 %s) at %dx%d on %s",
        info["model"],
        info["checkpoint"],
        (info["checkpoint_sha256"] or "")[:12],
        predictor.projection_config.height,
        predictor.projection_config.width,
        predictor.device,
    )
    return predictor


def cmd_predict(args: argparse.Namespace) -> int:
    """Predict every scan of a split or of chosen sequences into a predictions tree."""
    from rangeret.predict import predict_tree

    sequences = selected_sequences(args, load_label_config(None))
    predictor = predictor_from_args(args)
    summary = predict_tree(
        predictor,
        args.dataset,
        sequences,
        args.out,
        batch_size=args.batch_size,
        progress=not args.quiet,
    )
    print(summary.text())
    if not summary.ok:
        raise CommandError(
            f"{len(summary.failed)} of {summary.total} scans could not be predicted "
            f"(every other scan was written to {args.out})",
            [f"{k}: {v}" for k, v in summary.failed.items()],
        )
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    """Evaluate a predictions tree against ground truth with the official semantics."""
    from rangeret.evaluation import evaluate_predictions

    config = _label_config(args)
    sequences = selected_sequences(args, config)
    report = evaluate_predictions(
        args.dataset, args.predictions, sequences, config=config, progress=not args.quiet
    )
    print(report.table())
    for note in report.notes:
        log.warning(note)
    if args.json:
        report.write_json(args.json)
        print(f"report: {args.json}")
    if args.plots:
        from rangeret.plots import write_plots

        for path in write_plots(report, args.plots):
            print(f"plot: {path}")
    return 0


def cmd_submission(args: argparse.Namespace) -> int:
    """Write and validate the CodaLab/Codabench zip of a predictions tree."""
    from rangeret.submission import write_submission

    check = write_submission(
        args.predictions,
        args.dataset,
        args.out,
        allow_partial=args.allow_partial,
        description=args.description,
        config=_label_config(args),
        progress=not args.quiet,
    )
    print(check.summary())
    if check.partial:
        log.warning(
            "this is a partial archive: the benchmark server refuses it; use it for tests only"
        )
    return 0


def cmd_validate_submission(args: argparse.Namespace) -> int:
    """Validate a submission zip against the dataset and the official test split."""
    from rangeret.submission import validate_submission

    check = validate_submission(
        args.archive,
        args.dataset,
        allow_partial=args.allow_partial,
        config=_label_config(args),
        progress=not args.quiet,
    )
    if not check.ok:
        raise CommandError(
            f"{args.archive} would be refused: {len(check.problems)} problem(s), the first: "
            f"{check.problems[0]}",
            check.problems,
        )
    print(check.summary())
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    """Write a simulated dataset in the SemanticKITTI layout."""
    from rangeret.sim import SensorConfig, simulate_dataset

    counts: dict[str, int] = {}
    for item in args.sequences:
        name, _, number = item.partition(":")
        if not number.isdigit():
            raise CommandError(f"--sequences takes NAME:SCANS items such as 08:10, got {item!r}")
        counts[name] = int(number)
    labelled = [s for s in counts if s not in set(args.unlabelled)]
    sensor = SensorConfig(beams=args.beams, azimuth_steps=args.azimuth_steps)
    n = simulate_dataset(
        args.out, counts, labelled=labelled, sensor=sensor, seed=args.seed, progress=not args.quiet
    )
    print(f"{n} simulated scans in {args.out} ({', '.join(labelled) or 'none'} labelled)")
    return 0


def cmd_serve(args: argparse.Namespace) -> int:
    """Serve the HTTP gateway until interrupted."""
    from service.server import run_serve

    return run_serve(args)


def cmd_train(args: argparse.Namespace) -> int:
    """Train a network from a config and the command line (see `rangeret.training.command`)."""
    from rangeret.training import run_train

    return run_train(args)


def cmd_demo(args: argparse.Namespace) -> int:
    """Run evaluation and submission end to end on a small simulated example."""
    from workers.demo import run_demo

    run_demo(args.out, checkpoint=args.checkpoint, progress=not args.quiet)
    return 0


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The argument parser of the `rangeret` command and its subcommands.

    The options of `serve` and `train` need torch and the web stack; they are added only when
    `command` is one of them, or when it is None (every option), so other commands start quickly.
    """
    parser = argparse.ArgumentParser(
        prog="rangeret",
        description="RangeRet LiDAR semantic segmentation: evaluation, submissions and more.",
    )
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    common.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    splits = ("train", "valid", "test")

    p = sub.add_parser(
        "predict", parents=[common], help="label every scan of a split or of sequences"
    )
    p.add_argument("--dataset", type=Path, required=True, metavar="ROOT")
    add_selection(p, splits)
    p.add_argument(
        "--out", type=Path, required=True, metavar="PRED", help="predictions tree to write"
    )
    add_network_options(p)
    p.set_defaults(func=cmd_predict)

    p = sub.add_parser(
        "evaluate", parents=[common], help="per-class IoU of predictions against ground truth"
    )
    p.add_argument("--dataset", type=Path, required=True, metavar="ROOT")
    p.add_argument("--predictions", type=Path, required=True, metavar="PRED")
    add_selection(p, splits)
    p.add_argument("--json", type=Path, metavar="FILE", help="write the JSON report here")
    p.add_argument("--plots", type=Path, metavar="DIR", help="write confusion.png and iou.png here")
    _add_label_config(p)
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser(
        "submission", parents=[common], help="write and validate a CodaLab/Codabench zip"
    )
    p.add_argument("--predictions", type=Path, required=True, metavar="PRED")
    p.add_argument("--dataset", type=Path, required=True, metavar="ROOT")
    p.add_argument("--out", type=Path, required=True, metavar="FILE.zip")
    p.add_argument(
        "--allow-partial",
        action="store_true",
        help="accept a dataset with missing test sequences or scans (an archive for tests only)",
    )
    p.add_argument("--description", metavar="TEXT", help="text of description.txt in the archive")
    _add_label_config(p)
    p.set_defaults(func=cmd_submission)

    p = sub.add_parser(
        "validate-submission", parents=[common], help="check a submission zip before uploading it"
    )
    p.add_argument("archive", type=Path, metavar="FILE.zip")
    p.add_argument("--dataset", type=Path, required=True, metavar="ROOT")
    p.add_argument(
        "--allow-partial",
        action="store_true",
        help="accept a dataset with missing test sequences or scans (an archive for tests only)",
    )
    _add_label_config(p)
    p.set_defaults(func=cmd_validate_submission)

    p = sub.add_parser("serve", parents=[common], help="the HTTP gateway (FastAPI on uvicorn)")
    if command in (None, "serve"):
        from service.server import add_serve_arguments

        add_serve_arguments(p)
    p.set_defaults(func=cmd_serve)

    p = sub.add_parser(
        "train", parents=[common], help="train a network (in this process or with --ray)"
    )
    if command in (None, "train"):
        from rangeret.training import add_train_arguments

        add_train_arguments(p)
    p.set_defaults(func=cmd_train)

    p = sub.add_parser(
        "simulate", parents=[common], help="write a simulated dataset (street scenes)"
    )
    p.add_argument("--out", type=Path, required=True, metavar="ROOT")
    p.add_argument(
        "--sequences", nargs="+", required=True, metavar="XX:N", help="sequences and scan counts"
    )
    p.add_argument(
        "--unlabelled", nargs="*", default=[], metavar="XX", help="sequences written without labels"
    )
    p.add_argument("--beams", type=int, default=64)
    p.add_argument("--azimuth-steps", type=int, default=2048)
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser(
        "demo", parents=[common], help="the whole pipeline on a small simulated example"
    )
    p.add_argument("--out", type=Path, metavar="DIR", help="results folder (default: a new one)")
    p.add_argument(
        "--checkpoint",
        type=Path,
        metavar="FILE",
        help="other weights (default: the bundled demo weights)",
    )
    p.set_defaults(func=cmd_demo)
    return parser


_USER_ERRORS: tuple[type[BaseException], ...] = (
    ScanFormatError,
    DatasetLayoutError,
    EvaluationError,
    SubmissionError,
    FileNotFoundError,
    ValueError,  # CheckpointError and the other input errors of the library derive from it
)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `rangeret` command."""
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(next((a for a in argv if not a.startswith("-")), ""))
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
    return run_command(f"rangeret {args.command}", args.func, args)


def run_command(
    program: str, func: Callable[[argparse.Namespace], int], args: argparse.Namespace
) -> int:
    """Run a command's body; input errors become one line on stderr (details below it) and exit code 1.

    Every entry point (`rangeret`, `python -m service`, `python -m workers.predict_job`) goes through
    here, so users see the same message shape, and never a traceback, whatever they launched.
    """
    try:
        return func(args)
    except CommandError as exc:
        return fail(program, exc.reason, exc.details)
    except (EvaluationError, SubmissionError) as exc:
        return fail(program, _first_line(exc), exc.problems)
    except _USER_ERRORS as exc:
        return fail(program, str(exc))
    except KeyboardInterrupt:
        return fail(program, "interrupted", code=130)


def _first_line(exc: EvaluationError | SubmissionError) -> str:
    n = len(exc.problems)
    return f"{n} problem(s), the first: {exc.problems[0]}" if n else str(exc)


def fail(program: str, reason: str, details: Sequence[str] = (), code: int = 1) -> int:
    """Print `program: error: reason` and up to a screenful of details to stderr; return `code`."""
    print(f"{program}: error: {reason}", file=sys.stderr)
    if len(details) > 1:
        for line in details[:_MAX_DETAILS]:
            print(f"  - {line}", file=sys.stderr)
        if len(details) > _MAX_DETAILS:
            print(f"  ... and {len(details) - _MAX_DETAILS} more", file=sys.stderr)
    return code


if __name__ == "__main__":
    sys.exit(main())
