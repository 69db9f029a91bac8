"""What one benchmark owns: `Benchmark`, the base every entry of the registry
(`rangeret.submission.benchmarks`) derives from, and `DemoPlan`, what `rangeret demo` runs for it.

A benchmark (one dataset and task: SemanticKITTI semantic segmentation, nuScenes-lidarseg, ...)
owns its archive writer and validator with the official counts, its own command-line options of
`rangeret submission` and `validate-submission`, the zip a gateway job returns and the demo's
plan. How its IoU is scored is the profile's `benchmark.scoring`
(`rangeret.evaluation.scoring`); what its prediction files hold, the profile's
`benchmark.predictions` and its layout. The base class is also the entry of a profile without a
benchmark: its archives are refused in one sentence, its job zip is the predictions tree's files
and its demo predicts a validation sequence and a test sequence of the profile's splits.
"""

from __future__ import annotations

import argparse
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

from rangeret.dataset.layout import ScanEntry
from rangeret.dataset.profiles import DatasetProfile
from rangeret.evaluation.panoptic import PanopticRules
from rangeret.io.atomic import atomic_path
from rangeret.io.zipfiles import ReproducibleZip
from rangeret.sim.raycast import SensorConfig
from rangeret.submission.archives import SubmissionCheck, SubmissionError
from rangeret.submission.leaderboard import LeaderboardEntry


@dataclass(frozen=True)
class DemoPlan:
    """The simulated dataset `rangeret demo` predicts for a benchmark, what it evaluates and how
    it archives the predictions."""

    #: Scans to simulate per sequence.
    sequences: Mapping[str, int]
    #: The sequences simulated with ground truth, which the report scores.
    labelled: tuple[str, ...]
    #: The split the sequences were chosen by (a tables layout's predictions folder and the
    #: split its archive is for), or None.
    split: str | None = None
    #: The archive holds a few scans of the test split only (it is validated as partial).
    partial_archive: bool = True
    #: The simulated sensor (None: the profile's, `SensorConfig.for_profile`).
    sensor: SensorConfig | None = None
    #: Lines printed after the results: how to run the same on real data.
    hints: tuple[str, ...] = ()


@dataclass(frozen=True)
class ArchiveRequest:
    """What writing or checking a benchmark archive takes: the archive, the dataset and its
    profile, the benchmark's own options, and for writing the predictions and their record."""

    archive: Path
    dataset: Path
    profile: DatasetProfile
    #: The benchmark's options by destination (`Benchmark.option_dests`); None: not given.
    options: Mapping[str, Any] = field(default_factory=dict)
    #: A local dataset with missing test scans is accepted (an archive for tests only).
    allow_partial: bool = False
    progress: bool = False
    #: The predictions tree to archive (writing only).
    predictions: Path | None = None
    #: The text of `description.txt` (writing only).
    description: str = ""
    leaderboard: LeaderboardEntry = field(default_factory=LeaderboardEntry)
    checkpoint_sha256: str | None = None
    #: Threads that read and compress the predictions; the archive is the same for any number.
    workers: int | None = None

    def predictions_tree(self) -> Path:
        """The predictions tree to archive; a `SubmissionError` when none was given."""
        if self.predictions is None:
            raise SubmissionError([f"{self.archive}: no predictions tree was given to archive"])
        return self.predictions


@dataclass(frozen=True)
class JobPredictions:
    """A gateway job's predictions to zip: the scans `entries` of its `sequences`, predicted
    into `pred_root`, zipped at `path` with `description`; `sha256` names the checkpoint."""

    pred_root: Path
    entries: Sequence[ScanEntry]
    sequences: Sequence[str]
    path: Path
    description: str
    profile: DatasetProfile
    workers: int | None = None
    sha256: str | None = None


class Benchmark:
    """One benchmark and task; this base is also the entry of a profile without a benchmark."""

    #: The name profiles give in `benchmark.name`, and the registry looks up.
    name: str = ""
    #: How messages name it ("SemanticKITTI", "nuScenes-lidarseg").
    title: str = ""
    #: Whether it writes and checks submission archives (the base, for profiles without a
    #: benchmark, does not).
    writes_archives: bool = False
    #: How a panoptic benchmark scores objects (`rangeret.evaluation.panoptic`); None: a
    #: semantic benchmark, scored by the profile's `benchmark.scoring`.
    panoptic_rules: PanopticRules | None = None

    def check_profile(self, profile: DatasetProfile) -> str | None:
        """Why the benchmark cannot take the profile's data (its layout), or None."""
        return None

    # Command-line options of `rangeret submission` and `validate-submission` -----------------

    def add_arguments(self, parser: argparse.ArgumentParser, *, writing: bool) -> None:
        """Add the benchmark's own options (`writing`: of `submission`, else of
        `validate-submission`); their defaults must be None, meaning not given."""

    def option_dests(self, *, writing: bool) -> tuple[str, ...]:
        """The destinations of the options `add_arguments` adds."""
        return ()

    # Archives -----------------------------------------------------------------------------

    def write_archive(self, request: ArchiveRequest) -> SubmissionCheck:
        """Write and validate the benchmark archive of `request.predictions` at
        `request.archive`; a `SubmissionError` listing every problem, writing nothing."""
        raise SubmissionError([f"the {request.profile.name} profile has no benchmark archive"])

    def validate_archive(self, request: ArchiveRequest) -> SubmissionCheck:
        """Check `request.archive` as the benchmark's server would."""
        raise SubmissionError([f"the {request.profile.name} profile has no benchmark archive"])

    def write_job_zip(self, job: JobPredictions) -> None:
        """The predictions of a gateway job as a reproducible zip: each scan's prediction at its
        place in the predictions tree, with explicit directory entries and `description.txt`."""
        directories = sorted({d for e in job.entries for d in _parents(e.prediction)})
        zip_predictions(job, directories)

    # The demo -------------------------------------------------------------------------------

    def demo_plan(self, profile: DatasetProfile, valid_scans: int, test_scans: int) -> DemoPlan:
        """The first sequence of the profile's `valid` split, labelled, and one test sequence."""
        valid = profile.splits["valid"][0]
        tests = [s for s in profile.splits.get("test", ()) if s != valid][:1]
        return DemoPlan(
            sequences={valid: valid_scans, **{s: test_scans for s in tests}},
            labelled=(valid,),
            hints=REAL_DATA_HINTS,
        )


#: What the demo prints for a folder layout: the same run on real data with a published checkpoint.
REAL_DATA_HINTS = (
    "On real SemanticKITTI data with a published checkpoint:",
    "  rangeret predict --dataset ROOT --split valid --out PRED --checkpoint rangeret-kitti-657",
    "  rangeret evaluate --dataset ROOT --predictions PRED --split valid --json report.json "
    "--plots plots",
    "  RAY_AUTH_MODE=token ray job submit --working-dir . -- python -m workers.predict_job "
    "--dataset /abs/ROOT --split test \\",
    "      --out /abs/PRED --submission /abs/submission.zip --checkpoint rangeret-kitti-657"
    "   (a Ray job runs in a copy of the working directory: give absolute paths)",
    "  rangeret validate-submission /abs/submission.zip --dataset /abs/ROOT",
    "(a Ray cluster needs its token: see the README's Ray job recipe)",
)


def zip_predictions(job: JobPredictions, directories: Sequence[str]) -> None:
    """Zip the job's predictions at their places in its predictions tree, after the
    `directories` entries, with `description.txt`; reproducible whatever its `workers`."""
    with atomic_path(job.path) as tmp, ReproducibleZip(tmp) as zf:
        for name in directories:
            zf.add_directory(name)
        zf.add_files(
            (
                (entry.prediction, entry.prediction_in(job.pred_root).read_bytes)
                for entry in job.entries
            ),
            job.workers,
        )
        zf.add_file("description.txt", job.description.rstrip("\n") + "\n")


def _parents(relative: str) -> list[str]:
    """The folders above a relative file path, outermost first, each ending with `/`."""
    parents = list(PurePosixPath(relative).parents)[:-1]
    return [f"{p}/" for p in reversed(parents)]
