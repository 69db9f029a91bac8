"""The `rangeret` command: predict, evaluate, compare reports, submission archives, training and
simulation.

The library's own subcommands are defined here; `serve`, `demo` and `train --ray` come from the
layers above it through entry points (`rangeret.plugins`). Each subcommand exits 0 on success and
1 with a one-line reason (then the details) on any problem with its input; it never shows a
traceback for bad input.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from rangeret.commands import CommandError, run_command
from rangeret.dataset.profiles import DEFAULT_PROFILE, builtin_profiles, load_profile
from rangeret.options import (
    add_label_config,
    add_leaderboard_options,
    add_network_options,
    add_output_options,
    add_profile_option,
    add_selection,
    add_weights_options,
    label_config_from_args,
    leaderboard_from_args,
    profile_from_args,
    requested_profile,
    selected_sequences,
    spec_from_args,
    weights_spec_from_args,
)
from rangeret.plugins import COMMANDS_GROUP, Subcommand, load_plugins

if TYPE_CHECKING:
    from rangeret.inference.predictor import Predictor

log = logging.getLogger("rangeret")


def predictor_from_args(args: argparse.Namespace) -> Predictor:
    """A loaded `Predictor` from the shared network options, announced in the log."""
    predictor = spec_from_args(args).build()
    info = predictor.describe()
    log.info(
        "%s from %s (sha256 %s), %s profile, at %dx%d on %s",
        info["model"],
        info["checkpoint"],
        (info["checkpoint_sha256"] or "")[:12],
        predictor.profile.name,
        predictor.projection_config.height,
        predictor.projection_config.width,
        predictor.device,
    )
    return predictor


def cmd_predict(args: argparse.Namespace) -> int:
    """Predict every scan of a split or of chosen sequences into a predictions tree."""
    from rangeret.inference.runner import predict_tree

    predictor = predictor_from_args(args)
    sequences = selected_sequences(args, predictor.profile)
    summary = predict_tree(
        predictor,
        args.dataset,
        sequences,
        args.out,
        batch_size=args.batch_size,
        progress=not args.quiet,
        save_confidence=args.save_confidence,
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
    from rangeret.evaluation.evaluate import evaluate_predictions

    profile = profile_from_args(args)
    sequences = selected_sequences(args, profile)
    report = evaluate_predictions(
        args.dataset, args.predictions, sequences, progress=not args.quiet, profile=profile
    )
    print(report.table())
    for note in report.notes:
        log.warning(note)
    if args.json:
        report.write_json(args.json)
        print(f"report: {args.json}")
    if args.plots:
        from rangeret.evaluation.plots import write_plots

        for path in write_plots(report, args.plots, profile.labels):
            print(f"plot: {path}")
    return 0


def cmd_compare(args: argparse.Namespace) -> int:
    """Print the per-class IoU of evaluation reports side by side, with deltas against the first."""
    from rangeret.evaluation.compare import compare_reports

    if args.out is not None and args.out.suffix.lower() != ".png":
        raise CommandError(f"--out names the PNG to write, so it must end in .png, got {args.out}")
    comparison = compare_reports(args.reports)
    print(comparison.table())
    if args.out is not None:
        print(f"plot: {comparison.write_png(args.out)}")
    return 0


def _compare_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "reports",
        type=Path,
        nargs="+",
        metavar="REPORT.json",
        help="evaluation reports (of `rangeret evaluate --json`, the Ray job or a gateway job); "
        "the first is the baseline of the deltas",
    )
    p.add_argument(
        "--out", type=Path, metavar="FILE.png", help="also draw the comparison as grouped bars"
    )


def cmd_submission(args: argparse.Namespace) -> int:
    """Write and validate the CodaLab/Codabench zip of a predictions tree."""
    from rangeret.io.run_info import read_run_info
    from rangeret.submission.archives import write_submission
    from rangeret.submission.leaderboard import description_text

    _benchmark_profile_only(args)
    if args.workers is not None and args.workers < 1:
        raise CommandError(f"--workers must be at least 1, got {args.workers}")
    run = read_run_info(args.predictions)
    description = description_text(
        leaderboard_from_args(args),
        written_by="rangeret submission",
        checkpoint_sha256=run.get("checkpoint_sha256"),
        model=run.get("model"),
        profile=run.get("profile"),
        demo_weights=bool(run.get("demo_weights")),
        notes=[args.description] if args.description else [],
    )
    check = write_submission(
        args.predictions,
        args.dataset,
        args.out,
        allow_partial=args.allow_partial,
        description=description,
        config=label_config_from_args(args),
        progress=not args.quiet,
        workers=args.workers,
    )
    print(check.summary())
    if check.partial:
        log.warning(
            "this is a partial archive: the benchmark server refuses it; use it for tests only"
        )
    return 0


def cmd_validate_submission(args: argparse.Namespace) -> int:
    """Validate a submission zip against the dataset and the official test split."""
    from rangeret.submission.archives import validate_submission

    _benchmark_profile_only(args)
    check = validate_submission(
        args.archive,
        args.dataset,
        allow_partial=args.allow_partial,
        config=label_config_from_args(args),
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


def _benchmark_profile_only(args: argparse.Namespace) -> None:
    """Submission archives are the SemanticKITTI benchmark's format: other profiles are refused."""
    profile = profile_from_args(args)
    if profile.name != DEFAULT_PROFILE:
        raise CommandError(
            f"submission archives are the SemanticKITTI benchmark's format; the {profile.name} "
            "profile has no such archive (use `rangeret evaluate` on its predictions instead)"
        )


def cmd_view(args: argparse.Namespace) -> int:
    """Write a scan with its labels as a coloured PLY point cloud and a bird's-eye PNG."""
    from rangeret.evaluation.view import load_labelled_scan, write_view

    if args.out.suffix not in (".ply", ".png"):
        raise CommandError(
            f"--out {args.out}: the file must end with .ply (point cloud and PNG) or .png (PNG only)"
        )
    profile = profile_from_args(args)
    view = load_labelled_scan(args.scan, args.labels, args.ground_truth, profile)
    for path in write_view(view, args.out, profile):
        print(f"{path.suffix[1:]}: {path}")
    print(f"{len(view.points):,} points of {args.scan}, coloured by {view.coloured_by}")
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
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


def cmd_train(args: argparse.Namespace) -> int:
    """Train a network from a config and the command line (see `rangeret.cli.train`)."""
    from rangeret.cli.train import run_train

    return run_train(args)


def _predict_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dataset", type=Path, required=True, metavar="ROOT")
    add_selection(p)
    p.add_argument(
        "--out", type=Path, required=True, metavar="PRED", help="predictions tree to write"
    )
    p.add_argument(
        "--save-confidence",
        action="store_true",
        help="also write each point's confidence (the softmax probability of its label at its "
        "pixel) as float16 in PRED/sequences/XX/confidence/NNNNNN.npy",
    )
    add_network_options(p)


def _evaluate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dataset", type=Path, required=True, metavar="ROOT")
    p.add_argument("--predictions", type=Path, required=True, metavar="PRED")
    add_selection(p)
    p.add_argument("--json", type=Path, metavar="FILE", help="write the JSON report here")
    p.add_argument(
        "--plots",
        type=Path,
        metavar="DIR",
        help="write confusion.png, iou.png, iou-by-distance.png and miou-by-sequence.png here",
    )
    add_profile_option(p)
    add_label_config(p)


def _allow_partial_option(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--allow-partial",
        action="store_true",
        help="accept a dataset with missing test sequences or scans (an archive for tests only)",
    )


def _submission_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--predictions", type=Path, required=True, metavar="PRED")
    p.add_argument("--dataset", type=Path, required=True, metavar="ROOT")
    p.add_argument("--out", type=Path, required=True, metavar="FILE.zip")
    _allow_partial_option(p)
    add_leaderboard_options(p)
    p.add_argument(
        "--description",
        metavar="TEXT",
        help="free text for description.txt, after the leaderboard's lines and the checkpoint's "
        "SHA-256 (read from PRED/run.json)",
    )
    p.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="threads reading and compressing the labels (default: every CPU this process may "
        "use); the archive is the same for any N",
    )
    add_profile_option(p)
    add_label_config(p)


def _validate_submission_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("archive", type=Path, metavar="FILE.zip")
    p.add_argument("--dataset", type=Path, required=True, metavar="ROOT")
    _allow_partial_option(p)
    add_profile_option(p)
    add_label_config(p)


def _view_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scan", type=Path, metavar="SCAN", help="a .bin scan")
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


def _train_arguments(p: argparse.ArgumentParser) -> None:
    from rangeret.cli.train import add_train_arguments

    add_train_arguments(p)


def _simulate_arguments(p: argparse.ArgumentParser) -> None:
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


def cmd_profile(args: argparse.Namespace) -> int:
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
            selected_sequences(args, profile),
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


def cmd_weights(args: argparse.Namespace) -> int:
    """List the published models, or download one into the hub cache or a folder."""
    from rangeret.models.weights.hub import cached_weights, fetch_weights
    from rangeret.models.weights.registry import load_registry, lookup

    if args.action == "download":
        model = lookup(args.name)
        if model is None:
            known = ", ".join(sorted(load_registry()))
            raise CommandError(f"there is no published model {args.name!r}; known: {known}")
        path = fetch_weights(model, args.to)
        print(f"{model.name}: {path}")
        return 0
    rows = [("name", "dataset", "profile", "mIoU (%)", "cached", "size")]
    for model in load_registry().values():
        cached = cached_weights(model)
        size = cached.stat().st_size if cached else model.size
        rows.append(
            (
                model.name,
                model.dataset,
                model.profile,
                model.miou_text(),
                "yes" if cached else "no",
                f"{size / 2**20:.1f} MiB" if size else "unknown",
            )
        )
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    for row in rows:
        print(
            "  ".join(cell.ljust(width) for cell, width in zip(row, widths, strict=True)).rstrip()
        )
    return 0


def _weights_arguments(p: argparse.ArgumentParser) -> None:
    actions = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    actions.add_parser(
        "list", help="the published models: dataset, mIoU, whether cached here, and size"
    )
    download = actions.add_parser(
        "download",
        help="fetch a published model into the hub cache (HF_HOME) or a folder",
        description="Downloads go through huggingface_hub: HF_ENDPOINT, HF_HOME, HF_HUB_OFFLINE "
        "and HF_TOKEN apply.",
    )
    download.add_argument("name", metavar="NAME", help="a name of `rangeret weights list`")
    download.add_argument(
        "--to", type=Path, metavar="DIR", help="this folder instead of the hub cache"
    )


def cmd_export(args: argparse.Namespace) -> int:
    """Export a network to ONNX with the metadata a consumer needs, checked against torch."""
    from dataclasses import replace

    from rangeret.inference.runtime.onnx_export import ExportError, write_export
    from rangeret.io.scans import read_scan

    spec = replace(weights_spec_from_args(args), device="cpu", precision="fp32")
    predictor = spec.build()
    profile, config = predictor.profile, predictor.network.config
    scan = read_scan(args.check_scan, profile.points) if args.check_scan else None
    try:
        check = write_export(
            predictor.network,
            profile,
            args.out,
            dynamic_batch=args.dynamic_batch,
            checkpoint_sha256=predictor.checkpoint_sha256,
            scan=scan,
        )
    except ExportError as exc:
        raise CommandError(str(exc)) from exc
    print(check.text())
    print(
        f"{args.out}: {config.name} ({config.layers} blocks), {profile.name} profile, "
        f"({'N' if args.dynamic_batch else 1}, 5, {profile.projection.height}, "
        f"{profile.projection.width}) -> logits, checkpoint sha256 "
        f"{(predictor.checkpoint_sha256 or '')[:12]}"
    )
    return 0


def _export_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--format", default="onnx", choices=["onnx"], help="the file format (default onnx)"
    )
    p.add_argument("--out", type=Path, required=True, metavar="FILE.onnx", help="file to write")
    p.add_argument(
        "--dynamic-batch",
        action="store_true",
        help="a dynamic batch dimension (default: batch 1)",
    )
    p.add_argument(
        "--check-scan",
        type=Path,
        metavar="FILE",
        help="a .bin scan of the profile's sensor for the check against torch (default: a "
        "simulated street scan), beside fixed-seed noise",
    )
    add_weights_options(p.add_argument_group("network"))


def _profile_arguments(p: argparse.ArgumentParser) -> None:
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


#: The library's own subcommands, in the order `rangeret --help` lists them.
BUILTIN_COMMANDS = (
    Subcommand(
        "predict", "label every scan of a split or of sequences", _predict_arguments, cmd_predict
    ),
    Subcommand(
        "evaluate",
        "per-class IoU of predictions against ground truth",
        _evaluate_arguments,
        cmd_evaluate,
    ),
    Subcommand(
        "compare",
        "per-class IoU of evaluation reports side by side, deltas against the first",
        _compare_arguments,
        cmd_compare,
    ),
    Subcommand(
        "submission",
        "write and validate a CodaLab/Codabench zip",
        _submission_arguments,
        cmd_submission,
    ),
    Subcommand(
        "validate-submission",
        "check a submission zip before uploading it",
        _validate_submission_arguments,
        cmd_validate_submission,
    ),
    Subcommand(
        "view",
        "a scan with its labels as a coloured PLY point cloud and bird's-eye PNGs",
        _view_arguments,
        cmd_view,
    ),
    Subcommand(
        "train",
        "train a network (in this process, or with --ray on a cluster)",
        _train_arguments,
        cmd_train,
    ),
    Subcommand(
        "simulate",
        "write a simulated dataset (street scenes)",
        _simulate_arguments,
        cmd_simulate,
    ),
    Subcommand(
        "profile",
        "dataset profiles: list the built-in ones, show one as YAML",
        _profile_arguments,
        cmd_profile,
    ),
    Subcommand(
        "weights",
        "published models: list them, download one",
        _weights_arguments,
        cmd_weights,
    ),
    Subcommand(
        "export",
        "a network as ONNX with its metadata, checked against torch",
        _export_arguments,
        cmd_export,
        extra="onnx",
    ),
)


def subcommands() -> list[Subcommand]:
    """The library's subcommands, then those the installed layers contribute."""
    return [*BUILTIN_COMMANDS, *load_plugins(COMMANDS_GROUP)]


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The argument parser of the `rangeret` command and its subcommands.

    A subcommand's options are added only when `command` names it, or when it is None (every
    option): some need torch or the web stack, and other commands start without them. A
    command whose extra is not installed gets none (`main` refuses it before parsing).
    """
    parser = argparse.ArgumentParser(
        prog="rangeret",
        description="RangeRet LiDAR semantic segmentation: evaluation, submissions and more.",
    )
    common = argparse.ArgumentParser(add_help=False)
    add_output_options(common)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for cmd in subcommands():
        p = sub.add_parser(cmd.name, parents=[common], help=cmd.help)
        if (command is None or command == cmd.name) and cmd.installed():
            cmd.add_arguments(p)
        p.set_defaults(func=cmd.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `rangeret` command."""
    argv = sys.argv[1:] if argv is None else list(argv)
    name = next((a for a in argv if not a.startswith("-")), "")
    command = next((c for c in subcommands() if c.name == name), None)
    if command is not None and not command.installed():
        return run_command(f"rangeret {name}", command.refuse, argparse.Namespace())
    parser = build_parser(name)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
    return run_command(f"rangeret {args.command}", args.func, args)


if __name__ == "__main__":
    sys.exit(main())
