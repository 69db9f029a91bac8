"""SemanticKITTI semantic segmentation (CodaLab/Codabench): the registry's `semantickitti` entry.

Its archive is the test split's `sequences/XX/predictions/NNNNNN.label` files with every test
sequence's directory entries (`rangeret.submission.archives`); it takes no option of its own
and always holds the test split. A gateway job over test sequences only gets the same directory
entries, so its zip passes the validator; the demo simulates validation sequence 08 and short
test sequences 11 to 21 and writes a partial archive.
"""

from __future__ import annotations

from collections.abc import Sequence

from rangeret.dataset.profiles import DatasetProfile
from rangeret.sim.raycast import SensorConfig
from rangeret.submission.archives import (
    TEST_SEQUENCES,
    SubmissionCheck,
    required_directories,
    validate_submission,
    write_submission,
)
from rangeret.submission.benchmark import (
    REAL_DATA_HINTS,
    ArchiveRequest,
    Benchmark,
    DemoPlan,
    JobPredictions,
    zip_predictions,
)

#: The demo's labelled validation sequence.
DEMO_VALID = "08"


class SemanticKittiBenchmark(Benchmark):
    """The SemanticKITTI benchmark server's archive, validator, job zip and demo."""

    name = "semantickitti"
    title = "SemanticKITTI"
    writes_archives = True

    def check_profile(self, profile: DatasetProfile) -> str | None:
        """Its archives are made of folders of sequences."""
        if profile.layout.folders is None:
            return f"the {self.title} benchmark takes folders of sequences, not a version's tables"
        return None

    def things(self, profile: DatasetProfile) -> Sequence[int] | None:
        """The thing classes whose points a panoptic archive's labels must give objects; None:
        the semantic benchmark's archive, whose labels need none."""
        return None

    def write_archive(self, request: ArchiveRequest) -> SubmissionCheck:
        """The test split's zip, validated before it is moved into place."""
        return write_submission(
            request.predictions_tree(),
            request.dataset,
            request.archive,
            allow_partial=request.allow_partial,
            description=request.description,
            labels=request.profile.labels,
            progress=request.progress,
            workers=request.workers,
            things=self.things(request.profile),
        )

    def validate_archive(self, request: ArchiveRequest) -> SubmissionCheck:
        """What the official validator checks, and more (`validate_submission`)."""
        return validate_submission(
            request.archive,
            request.dataset,
            allow_partial=request.allow_partial,
            labels=request.profile.labels,
            progress=request.progress,
            things=self.things(request.profile),
        )

    def write_job_zip(self, job: JobPredictions) -> None:
        """A job over test sequences only gets every test sequence's directory entries, as the
        server wants; any other job, those of its own sequences."""
        if all(s in TEST_SEQUENCES for s in job.sequences):
            zip_predictions(job, list(required_directories()))
        else:
            super().write_job_zip(job)

    def demo_plan(self, profile: DatasetProfile, valid_scans: int, test_scans: int) -> DemoPlan:
        """Sequence 08 labelled, a few scans of each test sequence, a partial archive."""
        return DemoPlan(
            sequences={DEMO_VALID: valid_scans, **{s: test_scans for s in TEST_SEQUENCES}},
            labelled=(DEMO_VALID,),
            sensor=SensorConfig(beams=64, azimuth_steps=2048),
            hints=REAL_DATA_HINTS,
        )


SEMANTICKITTI = SemanticKittiBenchmark()
