"""`rangeret submission` and `rangeret validate-submission`: the CodaLab/Codabench zip of a
predictions tree, written and checked."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from rangeret.commands import CommandError
from rangeret.dataset.profiles import DEFAULT_PROFILE, DatasetProfile
from rangeret.options import (
    add_label_config,
    add_leaderboard_options,
    add_profile_option,
    leaderboard_from_args,
    profile_from_args,
)
from rangeret.plugins import Subcommand

log = logging.getLogger("rangeret")


def _allow_partial_option(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--allow-partial",
        action="store_true",
        help="accept a dataset with missing test sequences or scans (an archive for tests only)",
    )


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


def run_submission(args: argparse.Namespace) -> int:
    """Write and validate the CodaLab/Codabench zip of a predictions tree."""
    from rangeret.io.run_info import read_run_info
    from rangeret.submission.archives import write_submission
    from rangeret.submission.leaderboard import description_text

    profile = _benchmark_profile_only(args)
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
        labels=profile.labels,
        progress=not args.quiet,
        workers=args.workers,
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


def run_validate(args: argparse.Namespace) -> int:
    """Validate a submission zip against the dataset and the official test split."""
    from rangeret.submission.archives import validate_submission

    profile = _benchmark_profile_only(args)
    check = validate_submission(
        args.archive,
        args.dataset,
        allow_partial=args.allow_partial,
        labels=profile.labels,
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


def _benchmark_profile_only(args: argparse.Namespace) -> DatasetProfile:
    """The profile of --profile and --label-config, which must be SemanticKITTI's: submission
    archives are that benchmark's format, other profiles are refused."""
    profile = profile_from_args(args)
    if profile.name != DEFAULT_PROFILE:
        raise CommandError(
            f"submission archives are the SemanticKITTI benchmark's format; the {profile.name} "
            "profile has no such archive (use `rangeret evaluate` on its predictions instead)"
        )
    return profile


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
