"""A claimed job's work, from its folder to its final record.

`JobWork.run` checks the job may still be read as it was accepted (the profile its folder
records, scans that stay under the read roots), predicts every scan not yet written into
`<job>/predictions` with the executor, checks every prediction is there, writes the predictions
zip and, for the sequences with ground truth, the evaluation report and its plots, then stores
the job's final record. Everything is read with the dataset profile of the job's model (layout,
point record, labels) and, for a tables layout, the job's version and split; a job whose model
the gateway no longer serves fails, naming it. A panoptic job predicts objects too, into the
panoptic prediction paths, and its zip and report are its profile's panoptic benchmark's. When
the runner stops the job first (a cancel, or the gateway stopping), it returns without a final
record and the scheduler decides what becomes of the job.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

from rangeret.dataset.layout import ScanEntry, is_complete
from rangeret.dataset.profiles import DatasetProfile
from service.jobs.executors import JobControl, JobExecutor
from service.jobs.reasons import scrub
from service.jobs.results import (
    PREDICTIONS_ZIP,
    labelled_sequences,
    predictions_description,
    write_panoptic_report,
    write_predictions_zip,
    write_report,
)
from service.jobs.store import JobRecord, JobStore
from service.labelling.panoptic import panoptic_refusal
from service.models.catalog import ModelCatalog, ModelEntry
from service.paths import escaping_scans, outside_roots_sentence
from service.schemas import JobState

#: The file in a job's folder that names the profile the job was accepted for.
PROFILE_FILE = "profile.txt"
#: The folder in a job's folder its predictions are written to.
PREDICTIONS_DIR = "predictions"


def accepted_profile(folder: Path) -> str | None:
    """The profile name a job's folder records; None for a job from before it was recorded."""
    try:
        return (folder / PROFILE_FILE).read_text().strip() or None
    except FileNotFoundError:
        return None


class JobWork:
    """Does the work of one claimed job at a time (one instance serves every runner thread).

    `read_roots`, when given, are the folders (resolved) the job's scans must lie under when
    they are read; `on_scans(count, model)` is told of every batch of newly written predictions.
    """

    def __init__(
        self,
        store: JobStore,
        executor: JobExecutor,
        models: ModelCatalog,
        read_roots: Sequence[Path] | None = None,
        on_scans: Callable[[int, str], None] | None = None,
    ) -> None:
        self.store = store
        self.executor = executor
        self.models = models
        self.read_roots = None if read_roots is None else list(read_roots)
        self.on_scans = on_scans

    def run(self, job: JobRecord, folder: Path, control: JobControl) -> bool:
        """Do `job`'s work in its `folder` and store its final record (succeeded or failed);
        False when `control` was set before the predictions were through (nothing final
        stored). `JobError` and other exceptions are the caller's to record."""
        out = folder / PREDICTIONS_DIR
        model = self.models.entries.get(job.model or self.models.default)
        if model is None:
            reason = (
                f"the job's model {job.model} is no longer served (this gateway serves "
                f"{', '.join(self.models.names)})"
            )
            self.store.finish(job.id, JobState.failed, reason=reason)
            return True
        profile = model.profile
        refusal = self._profile_refusal(folder, profile)
        if refusal is None and job.panoptic:
            refusal = panoptic_refusal(profile, model.name)
        if refusal is not None:
            self.store.finish(job.id, JobState.failed, reason=refusal)
            return True
        entries = job.selection(profile.layout).scans()
        escaping = escaping_scans(entries, self.read_roots) if self.read_roots else []
        if escaping:
            self.store.finish(
                job.id, JobState.failed, reason=outside_roots_sentence(escaping, "The job")
            )
            return True
        failures = self._predict(job, model, entries, out, control)
        if control.is_set():
            return False
        if failures:
            self.store.finish(
                job.id,
                JobState.failed,
                reason=f"{len(failures)} of {len(entries)} scans could not be predicted (see errors)",
                errors=[
                    f"{key}: {scrub(reason, folder, self.read_roots)}"
                    for key, reason in failures.items()
                ],
            )
            return True
        missing = self._missing(job, profile, entries, folder, out)
        if missing is not None:
            self.store.finish(job.id, JobState.failed, reason=missing)
            return True
        self.store.progress(job.id, len(entries), len(entries), 0)
        self._finish(job, model, entries, folder, out)
        return True

    @staticmethod
    def _profile_refusal(folder: Path, profile: DatasetProfile) -> str | None:
        """Why a job accepted for another profile than its model's now is not read; None when
        it was accepted for this one (or before profiles were recorded)."""
        accepted = accepted_profile(folder)
        if accepted is None or accepted == profile.name:
            return None
        return (
            f"the job was accepted for the {accepted} profile, and its model now runs with "
            f"the {profile.name} profile"
        )

    def _predict(
        self,
        job: JobRecord,
        model: ModelEntry,
        entries: list[ScanEntry],
        out: Path,
        control: JobControl,
    ) -> dict[str, str]:
        """Predict the scans not yet written with the job's model, keeping the job's progress
        (and the scan count) up to date; the failures by scan key."""
        record = model.profile.points
        skipped = sum(is_complete(e, out, record=record) for e in entries)
        self.store.progress(job.id, len(entries), skipped, 0)
        counted = [0]

        def progress(seen: int, failed: int, _pending: int) -> None:
            written = seen - failed
            self.store.progress(job.id, len(entries), skipped + written, failed)
            if self.on_scans is not None and written > counted[0]:
                self.on_scans(written - counted[0], model.name)
                counted[0] = written

        # An executor is asked for objects only by a panoptic job.
        objects = {"panoptic": True} if job.panoptic else {}
        return self.executor.predict(
            entries,
            Path(job.dataset),
            job.sequences,
            out,
            progress,
            control,
            model=model.name,
            **objects,
        )

    def _missing(
        self,
        job: JobRecord,
        profile: DatasetProfile,
        entries: list[ScanEntry],
        folder: Path,
        out: Path,
    ) -> str | None:
        """Why the job fails when predictions are missing from its folder once they were all
        written (it was changed meanwhile), with the progress set back; None when all are there."""
        missing = [e for e in entries if not is_complete(e, out, record=profile.points)]
        if not missing:
            return None
        self.store.progress(job.id, len(entries), len(entries) - len(missing), 0)
        shown = ", ".join(e.prediction_in(out).relative_to(folder).as_posix() for e in missing[:5])
        return (
            f"{len(missing)} of {len(entries)} predictions are missing from the job's "
            f"folder ({shown}{', ...' if len(missing) > 5 else ''}): it was changed or "
            "removed while the job ran"
        )

    def _finish(
        self, job: JobRecord, model: ModelEntry, entries: list[ScanEntry], folder: Path, out: Path
    ) -> None:
        """Write the predictions zip and, for labelled sequences, the report and its plots;
        store the job as succeeded with them."""
        profile = model.profile
        selection = job.selection(profile.layout)
        zip_path = folder / PREDICTIONS_ZIP
        sha = model.checkpoint_sha256
        description = predictions_description(sha, profile)
        write_predictions_zip(
            out,
            entries,
            job.sequences,
            zip_path,
            description,
            profile=profile,
            sha256=sha,
            panoptic=job.panoptic,
        )
        metrics = report_path = None
        labelled = labelled_sequences(selection)
        if labelled:
            scored = (write_panoptic_report if job.panoptic else write_report)(
                selection.only(labelled),
                out,
                folder,
                profile=profile,
                checkpoint_sha256=model.checkpoint_sha256,
                precision=self.executor.precision,
                backend=self.executor.inference_backend,
            )
            if scored is not None:
                report_path, metrics = scored
        self.store.finish(
            job.id, JobState.succeeded, metrics=metrics, predictions=zip_path, report=report_path
        )
