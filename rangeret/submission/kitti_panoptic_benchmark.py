"""SemanticKITTI panoptic segmentation (Codabench competition 13666): the registry's
`semantickitti-panoptic` entry.

Its archive is the semantic benchmark's (the test split's `sequences/XX/predictions/NNNNNN.label`
files with every test sequence's directory entries), each label holding `instance << 16 | raw
id`; the validator also refuses an archive whose thing points carry no instance at all (semantic
labels sent to the panoptic benchmark). Scored as the benchmark's `evaluate_panoptic.py` scores
(`rangeret.evaluation.panoptic`: PQ, SQ, RQ, PQ-dagger and IoU, instances of fewer than 50 points
left out of the false positives and negatives).
"""

from __future__ import annotations

from rangeret.evaluation.panoptic import KITTI_PANOPTIC, PanopticRules
from rangeret.submission.archives import SubmissionCheck, validate_submission, write_submission
from rangeret.submission.benchmark import ArchiveRequest
from rangeret.submission.kitti_benchmark import SemanticKittiBenchmark


class SemanticKittiPanopticBenchmark(SemanticKittiBenchmark):
    """The SemanticKITTI panoptic server's archive, validator, job zip and demo."""

    name = "semantickitti-panoptic"
    title = "SemanticKITTI panoptic"
    panoptic_rules: PanopticRules | None = KITTI_PANOPTIC

    def write_archive(self, request: ArchiveRequest) -> SubmissionCheck:
        """The test split's zip of panoptic labels, validated before it is moved into place."""
        return write_submission(
            request.predictions_tree(),
            request.dataset,
            request.archive,
            allow_partial=request.allow_partial,
            description=request.description,
            labels=request.profile.labels,
            progress=request.progress,
            workers=request.workers,
            things=request.profile.things,
        )

    def validate_archive(self, request: ArchiveRequest) -> SubmissionCheck:
        """The semantic archive's checks, and instances in the thing points."""
        return validate_submission(
            request.archive,
            request.dataset,
            allow_partial=request.allow_partial,
            labels=request.profile.labels,
            progress=request.progress,
            things=request.profile.things,
        )


SEMANTICKITTI_PANOPTIC = SemanticKittiPanopticBenchmark()
