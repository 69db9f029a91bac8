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

from collections.abc import Sequence

from rangeret.dataset.profiles import DatasetProfile
from rangeret.evaluation.panoptic import KITTI_PANOPTIC, PanopticRules
from rangeret.submission.kitti_benchmark import SemanticKittiBenchmark


class SemanticKittiPanopticBenchmark(SemanticKittiBenchmark):
    """The SemanticKITTI panoptic server's archive, validator, job zip and demo."""

    name = "semantickitti-panoptic"
    title = "SemanticKITTI panoptic"
    panoptic_rules: PanopticRules | None = KITTI_PANOPTIC

    def things(self, profile: DatasetProfile) -> Sequence[int] | None:
        """The profile's thing classes: each archive's labels must carry objects in them."""
        return profile.things


SEMANTICKITTI_PANOPTIC = SemanticKittiPanopticBenchmark()
