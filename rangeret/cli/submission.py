"""`rangeret submission` and `rangeret validate-submission`: the benchmark zip of a predictions
tree, written and checked: SemanticKITTI's for CodaLab/Codabench, or nuScenes-lidarseg's results
folder with the `nuscenes` profile."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

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

log = logging.getLogger("rangeret")


def _allow_partial_option(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--allow-partial",
        action="store_true",
        help="accept a dataset with missing test sequences or scans (an archive for tests only)",
    )


#: submission.json's meta flags, as their options' destinations.
META_OPTIONS = ("use_camera", "use_lidar", "use_radar", "use_map", "use_external")


def _nuscenes_options(p: argparse.ArgumentParser, *, meta: bool) -> None:
    """--split and --version of a nuScenes archive, and with `meta` submission.json's flags."""
    group = p.add_argument_group("nuScenes-lidarseg (--profile nuscenes)")
    group.add_argument(
        "--split",
        metavar="SPLIT",
        help="the split the archive is for (default test; also val, mini_val, ...)",
    )
    group.add_argument(
        "--version", metavar="VERSION", help="the version folder (default: the one ROOT holds)"
    )
    if not meta:
        return
    for key, on in (
        ("camera", False),
        ("lidar", True),
        ("radar", False),
        ("map", False),
        ("external", False),
    ):
        group.add_argument(
            f"--use-{key}",
            action=argparse.BooleanOptionalAction,
            default=None,
            help=f"submission.json's meta.use_{key} (default {'true' if on else 'false'})",
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
    _nuscenes_options(p, meta=True)


def run_submission(args: argparse.Namespace) -> int:
    """Write and validate the benchmark zip of a predictions tree."""
    from rangeret.io.run_info import read_run_info
    from rangeret.submission.benchmarks import write_benchmark_archive
    from rangeret.submission.leaderboard import description_text
    from rangeret.submission.nuscenes import SubmissionMeta

    profile = _benchmark_profile(args)
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
    meta = None
    if profile.layout.kind == "tables":
        defaults = SubmissionMeta()
        meta = SubmissionMeta(
            **{
                name: getattr(defaults, name)
                if getattr(args, name) is None
                else getattr(args, name)
                for name in META_OPTIONS
            }
        )
    check = write_benchmark_archive(
        profile,
        args.predictions,
        args.dataset,
        args.out,
        description=description,
        leaderboard=leaderboard_from_args(args),
        checkpoint_sha256=run.get("checkpoint_sha256"),
        split=args.split,
        version=args.version,
        meta=meta,
        allow_partial=args.allow_partial,
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
    _nuscenes_options(p, meta=False)


def run_validate(args: argparse.Namespace) -> int:
    """Validate a submission zip against the dataset and the official test split."""
    from rangeret.submission.archives import validate_submission
    from rangeret.submission.nuscenes import validate_nuscenes_submission

    profile = _benchmark_profile(args)
    if profile.layout.kind == "tables":
        check = validate_nuscenes_submission(
            args.archive,
            args.dataset,
            args.split or "test",
            profile=profile,
            version=args.version,
            allow_partial=args.allow_partial,
            progress=not args.quiet,
        )
    else:
        check = validate_submission(
            args.archive,
            args.dataset,
            allow_partial=args.allow_partial,
            labels=profile.labels,
            progress=not args.quiet,
        )
    if not check.ok:
        problems = check.problems
        if len(problems) == 1:
            raise CommandError(f"{args.archive} would be refused: {problems[0]}")
        raise CommandError(
            f"{args.archive} would be refused for {len(problems)} problems:", problems
        )
    print(check.summary())
    return 0


def _benchmark_profile(args: argparse.Namespace) -> DatasetProfile:
    """The profile of --profile and --label-config, which must be a benchmark's: SemanticKITTI's
    or one of nuScenes' tables; other profiles are refused, and so are nuScenes' options with
    SemanticKITTI."""
    from rangeret.submission.benchmarks import no_archive_reason

    profile = profile_from_args(args)
    if profile.layout.kind == "tables":
        return profile
    reason = no_archive_reason(profile)
    if reason is not None:
        raise CommandError(reason)
    given = [
        option
        for option, value in (
            ("--split", args.split),
            ("--version", args.version),
            *(("--" + k.replace("_", "-"), getattr(args, k, None)) for k in META_OPTIONS),
        )
        if value is not None
    ]
    if given:
        raise CommandError(
            f"{given[0]} is for nuScenes-lidarseg archives (--profile nuscenes); a SemanticKITTI "
            "archive always holds the test split"
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
