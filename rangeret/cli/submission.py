"""`rangeret submission` and `rangeret validate-submission`: the benchmark zip of a predictions
tree, written and checked by the benchmark the profile names (`rangeret.submission.benchmarks`):
SemanticKITTI's for CodaLab/Codabench, nuScenes-lidarseg's results folder with the `nuscenes`
profile, or another registered benchmark's. Each benchmark adds its own options."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rangeret.commands import CommandError
from rangeret.dataset.profiles import DatasetProfile
from rangeret.options import (
    add_label_config,
    add_leaderboard_options,
    add_profile_option,
    leaderboard_from_args,
    profile_from_args,
)
from rangeret.plugins import Subcommand

if TYPE_CHECKING:
    from rangeret.submission.benchmark import ArchiveRequest, Benchmark

log = logging.getLogger("rangeret")


def _allow_partial_option(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--allow-partial",
        action="store_true",
        help="accept a dataset with missing test sequences or scans (an archive for tests only)",
    )


#: The tasks of --task: semantic segmentation, or objects too (the profile's panoptic benchmark).
TASKS = {"semantic": False, "panoptic": True}


def _benchmark_options(p: argparse.ArgumentParser, *, writing: bool) -> None:
    """--task, and every registered benchmark's own options, each in its group (a benchmark
    whose options another one added already, its semantic sibling's, adds none)."""
    from rangeret.submission.benchmarks import registered

    p.add_argument(
        "--task",
        choices=list(TASKS),
        default="semantic",
        help="semantic: the profile's semantic benchmark (default); panoptic: its panoptic one "
        "(SemanticKITTI panoptic, nuScenes-panoptic), of predictions made with --panoptic",
    )
    added: set[str] = set()
    for benchmark in registered().values():
        dests = set(benchmark.option_dests(writing=writing))
        if dests and dests <= added:
            continue
        benchmark.add_arguments(p, writing=writing)
        added |= dests


def add_submission_arguments(p: argparse.ArgumentParser) -> None:
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
    _benchmark_options(p, writing=True)


def run_submission(args: argparse.Namespace) -> int:
    """Write and validate the benchmark zip of a predictions tree."""
    from rangeret.io.run_info import read_run_info
    from rangeret.submission.leaderboard import description_text

    profile, benchmark, options = _benchmark_profile(args, writing=True)
    if args.workers is not None and args.workers < 1:
        raise CommandError(f"--workers must be at least 1, got {args.workers}")
    run = read_run_info(args.predictions)
    leaderboard = leaderboard_from_args(args)
    description = description_text(
        leaderboard,
        written_by="rangeret submission",
        checkpoint_sha256=run.get("checkpoint_sha256"),
        model=run.get("model"),
        profile=run.get("profile"),
        demo_weights=bool(run.get("demo_weights")),
        notes=[args.description] if args.description else [],
    )
    check = benchmark.write_archive(
        _request(
            args,
            profile,
            options,
            args.out,
            predictions=args.predictions,
            description=description,
            leaderboard=leaderboard,
            checkpoint_sha256=run.get("checkpoint_sha256"),
            workers=args.workers,
        )
    )
    print(check.summary())
    if check.partial:
        log.warning(
            "this is a partial archive: the benchmark server refuses it; use it for tests only"
        )
    return 0


def add_validate_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("archive", type=Path, metavar="FILE.zip")
    p.add_argument("--dataset", type=Path, required=True, metavar="ROOT")
    _allow_partial_option(p)
    add_profile_option(p)
    add_label_config(p)
    _benchmark_options(p, writing=False)


def run_validate(args: argparse.Namespace) -> int:
    """Validate a submission zip against the dataset and the official test split."""
    profile, benchmark, options = _benchmark_profile(args, writing=False)
    check = benchmark.validate_archive(_request(args, profile, options, args.archive))
    if not check.ok:
        problems = check.problems
        if len(problems) == 1:
            raise CommandError(f"{args.archive} would be refused: {problems[0]}")
        raise CommandError(
            f"{args.archive} would be refused for {len(problems)} problems:", problems
        )
    print(check.summary())
    return 0


def _request(
    args: argparse.Namespace,
    profile: DatasetProfile,
    options: dict[str, Any],
    archive: Path,
    **writing: Any,
) -> ArchiveRequest:
    """The archive request of the command line: --dataset, --allow-partial, -q, and the
    `writing` fields of `submission`."""
    from rangeret.submission.benchmark import ArchiveRequest

    return ArchiveRequest(
        archive,
        args.dataset,
        profile,
        options,
        allow_partial=args.allow_partial,
        progress=not args.quiet,
        **writing,
    )


def _benchmark_profile(
    args: argparse.Namespace, *, writing: bool
) -> tuple[DatasetProfile, Benchmark, dict[str, Any]]:
    """The profile of --profile and --label-config, its benchmark and that benchmark's options;
    a profile without a benchmark archive is refused, and so are other benchmarks' options."""
    from rangeret.submission.benchmarks import benchmark_of, no_archive_reason, registered

    profile = profile_from_args(args)
    panoptic = TASKS[args.task]
    reason = no_archive_reason(profile, panoptic=panoptic)
    if reason is not None:
        raise CommandError(reason)
    benchmark = benchmark_of(profile, panoptic=panoptic)
    own = benchmark.option_dests(writing=writing)
    for other in registered().values():
        for dest in other.option_dests(writing=writing):
            if dest not in own and getattr(args, dest, None) is not None:
                raise CommandError(
                    f"--{dest.replace('_', '-')} is an option of {other.title} archives; the "
                    f"{profile.name} profile's are {benchmark.title}'s"
                )
    return profile, benchmark, {dest: getattr(args, dest, None) for dest in own}


COMMAND = Subcommand(
    "submission",
    "write and validate a CodaLab/Codabench zip",
    add_submission_arguments,
    run_submission,
)

VALIDATE_COMMAND = Subcommand(
    "validate-submission",
    "check a submission zip before uploading it",
    add_validate_arguments,
    run_validate,
)
