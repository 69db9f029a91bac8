"""The benchmark archive of a profile, whichever its benchmark: every runner that writes one
(`rangeret submission`, the Ray job) goes through `write_benchmark_archive`.

SemanticKITTI's profile writes the CodaLab/Codabench zip of its test split
(`rangeret.submission.archives`); a profile of nuScenes' tables writes the nuScenes-lidarseg
results folder of a split (`rangeret.submission.nuscenes`). Other profiles have no benchmark
archive.
"""

from __future__ import annotations

from pathlib import Path

from rangeret.dataset.profiles import DEFAULT_PROFILE, DatasetProfile
from rangeret.submission.archives import SubmissionCheck, SubmissionError, write_submission
from rangeret.submission.leaderboard import LeaderboardEntry
from rangeret.submission.nuscenes import (
    SubmissionMeta,
    submission_json,
    write_nuscenes_submission,
)


def no_archive_reason(profile: DatasetProfile) -> str | None:
    """Why the profile has no benchmark archive, or None where it has one."""
    if profile.layout.kind == "tables" or profile.name == DEFAULT_PROFILE:
        return None
    return (
        "submission archives are the SemanticKITTI and nuScenes-lidarseg benchmarks' formats; "
        f"the {profile.name} profile has no such archive (use `rangeret evaluate` on its "
        "predictions instead)"
    )


def write_benchmark_archive(
    profile: DatasetProfile,
    predictions: Path | str,
    dataset: Path | str,
    out: Path | str,
    *,
    description: str,
    leaderboard: LeaderboardEntry,
    checkpoint_sha256: str | None,
    split: str | None = None,
    version: str | None = None,
    meta: SubmissionMeta | None = None,
    allow_partial: bool = False,
    progress: bool = False,
    workers: int | None = None,
) -> SubmissionCheck:
    """Write and validate the archive of a predictions tree for the profile's benchmark
    (nuScenes: of `split`, default test, with `meta` in submission.json); a profile without
    one is a `SubmissionError` saying so."""
    if profile.layout.kind == "tables":
        meta = meta or SubmissionMeta()
        return write_nuscenes_submission(
            predictions,
            dataset,
            out,
            split or "test",
            profile=profile,
            meta=meta,
            submission=submission_json(meta, leaderboard, checkpoint_sha256),
            description=description,
            version=version,
            allow_partial=allow_partial,
            progress=progress,
            workers=workers,
        )
    reason = no_archive_reason(profile)
    if reason is not None:
        raise SubmissionError([reason])
    return write_submission(
        predictions,
        dataset,
        out,
        allow_partial=allow_partial,
        description=description,
        labels=profile.labels,
        progress=progress,
        workers=workers,
    )
