"""nuScenes-lidarseg and nuScenes-panoptic: the registry's `nuscenes-lidarseg` and
`nuscenes-panoptic` entries.

Its archive is the devkit's results folder of one split (`rangeret.submission.nuscenes`); its own
options choose the split (default test) and the version folder, and when writing, the five meta
flags of `submission.json` (`--use-camera` ...). A gateway job's zip is the results folder of the
splits its keyframes' predictions lie in; the demo simulates v1.0-mini's mini_val scenes and
writes their whole results folder. nuScenes-panoptic's archive is the same with `panoptic/`
`.npz` files and `"task": "segmentation"` in submission.json's meta, scored as the devkit's
`NuScenesPanopticEval` scores (`rangeret.evaluation.panoptic`).
"""

from __future__ import annotations

import argparse

from rangeret.dataset.profiles import DatasetProfile
from rangeret.evaluation.panoptic import DEVKIT_PANOPTIC, PanopticRules
from rangeret.submission.archives import SubmissionCheck
from rangeret.submission.benchmark import ArchiveRequest, Benchmark, DemoPlan, JobPredictions
from rangeret.submission.leaderboard import LeaderboardEntry
from rangeret.submission.nuscenes import (
    LIDARSEG_RESULTS,
    META_KEYS,
    PANOPTIC_RESULTS,
    ResultsFormat,
    SubmissionMeta,
    submission_json,
    validate_nuscenes_submission,
    write_nuscenes_results,
    write_nuscenes_submission,
)

#: The split an archive is for when --split is left out.
DEFAULT_SPLIT = "test"
#: The split the demo simulates and archives.
DEMO_SPLIT = "mini_val"
_FLAG_DEFAULTS = SubmissionMeta()


class NuScenesLidarsegBenchmark(Benchmark):
    """The nuScenes-lidarseg challenge's results folder, validator, job zip and demo."""

    name = "nuscenes-lidarseg"
    title = "nuScenes-lidarseg"
    writes_archives = True
    #: What its results folder holds.
    results: ResultsFormat = LIDARSEG_RESULTS

    def check_profile(self, profile: DatasetProfile) -> str | None:
        """Its archives are made of a version's tables."""
        if profile.layout.folders is not None:
            return f"the {self.title} benchmark takes a version's tables, not folders of sequences"
        return None

    def add_arguments(self, parser: argparse.ArgumentParser, *, writing: bool) -> None:
        """--split and --version, and when writing submission.json's meta flags."""
        group = parser.add_argument_group("nuScenes-lidarseg and -panoptic (--profile nuscenes)")
        group.add_argument(
            "--split",
            metavar="SPLIT",
            help=f"the split the archive is for (default {DEFAULT_SPLIT}; also val, mini_val, ...)",
        )
        group.add_argument(
            "--version", metavar="VERSION", help="the version folder (default: the one ROOT holds)"
        )
        if not writing:
            return
        for key in META_KEYS:
            flag = key.removeprefix("use_")
            on = getattr(_FLAG_DEFAULTS, key)
            group.add_argument(
                f"--use-{flag}",
                action=argparse.BooleanOptionalAction,
                default=None,
                help=f"submission.json's meta.{key} (default {'true' if on else 'false'})",
            )

    def option_dests(self, *, writing: bool) -> tuple[str, ...]:
        """split, version and the meta flags' keys."""
        return ("split", "version", *(META_KEYS if writing else ()))

    def write_archive(self, request: ArchiveRequest) -> SubmissionCheck:
        """The results folder of the split, with submission.json's meta from the options."""
        options = request.options
        meta = SubmissionMeta(
            **{
                key: getattr(_FLAG_DEFAULTS, key) if options.get(key) is None else options[key]
                for key in META_KEYS
            }
        )
        return write_nuscenes_submission(
            request.predictions_tree(),
            request.dataset,
            request.archive,
            options.get("split") or DEFAULT_SPLIT,
            profile=request.profile,
            meta=meta,
            submission=submission_json(
                meta, request.leaderboard, request.checkpoint_sha256, self.results
            ),
            description=request.description,
            version=options.get("version"),
            allow_partial=request.allow_partial,
            progress=request.progress,
            workers=request.workers,
            results=self.results,
        )

    def validate_archive(self, request: ArchiveRequest) -> SubmissionCheck:
        """Every check of the devkit's validator, and the project's own."""
        return validate_nuscenes_submission(
            request.archive,
            request.dataset,
            request.options.get("split") or DEFAULT_SPLIT,
            profile=request.profile,
            version=request.options.get("version"),
            allow_partial=request.allow_partial,
            progress=request.progress,
            results=self.results,
        )

    def write_job_zip(self, job: JobPredictions) -> None:
        """Each split folder of the job's predictions with its submission.json naming the
        checkpoint."""
        write_nuscenes_results(
            job.pred_root,
            job.entries,
            job.path,
            profile=job.profile,
            submission=submission_json(
                _FLAG_DEFAULTS, LeaderboardEntry(), job.sha256, self.results
            ),
            description=job.description,
            workers=job.workers,
            results=self.results,
        )

    def demo_plan(self, profile: DatasetProfile, valid_scans: int, test_scans: int) -> DemoPlan:
        """Both mini_val scenes, labelled, evaluated and archived whole."""
        scenes = tuple(profile.splits[DEMO_SPLIT])
        return DemoPlan(
            sequences={scene: max(1, valid_scans // 2) for scene in scenes},
            labelled=scenes,
            split=DEMO_SPLIT,
            partial_archive=False,
            hints=(
                "On a real nuScenes tree with weights for it:",
                "  rangeret predict --profile nuscenes --dataset ROOT --split val --out PRED "
                "--checkpoint FILE",
                "  rangeret evaluate --profile nuscenes --dataset ROOT --predictions PRED "
                "--split val --json report.json",
                "  rangeret submission --profile nuscenes --dataset ROOT --predictions PRED "
                "--split test --out submission.zip",
            ),
        )


NUSCENES_LIDARSEG = NuScenesLidarsegBenchmark()


class NuScenesPanopticBenchmark(NuScenesLidarsegBenchmark):
    """The nuScenes-panoptic challenge's results folder, validator, job zip and demo: the
    lidarseg ones with panoptic files, sharing their options."""

    name = "nuscenes-panoptic"
    title = "nuScenes-panoptic"
    results = PANOPTIC_RESULTS
    panoptic_rules: PanopticRules | None = DEVKIT_PANOPTIC


NUSCENES_PANOPTIC = NuScenesPanopticBenchmark()
