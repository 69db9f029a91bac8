"""A job's result files in its folder: the predictions zip, the evaluation report and its plots.

A job writes `predictions.zip` (a folder layout's scans as `sequences/XX/predictions/*.label`, a
tables layout's as nuScenes' results folder, `lidarseg/<split>/` with `<split>/submission.json`;
each with a `description.txt`) and, for the sequences with ground truth, `report.json` and the
report's PNGs under `plots/`, as `rangeret evaluate --plots` draws them. The routes serve those
files.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

from rangeret.dataset.layout import DatasetLayout, ScanEntry, discover
from rangeret.dataset.profiles import DatasetProfile
from rangeret.evaluation.evaluate import evaluate_predictions
from rangeret.evaluation.plots import write_plots
from rangeret.io.atomic import atomic_path
from rangeret.io.zipfiles import ReproducibleZip
from rangeret.submission.archives import TEST_SEQUENCES, required_directories
from rangeret.submission.leaderboard import LeaderboardEntry, description_text
from rangeret.submission.nuscenes import SubmissionMeta, submission_json, write_nuscenes_results
from service.jobs.store import JobRecord
from service.schemas import JobState

PREDICTIONS_ZIP = "predictions.zip"
REPORT_JSON = "report.json"
#: The folder of a labelled job's report PNGs (those of `rangeret evaluate --plots`).
PLOTS_DIR = "plots"
#: A report PNG's name, as `rangeret.evaluation.plots.write_plots` names them.
PLOT_NAME = re.compile(r"^[a-z][a-z-]{0,63}\.png$")
#: The profile whose test sequences the benchmark server takes (`rangeret.submission.archives`).
BENCHMARK_PROFILE = "semantickitti"


def labelled_sequences(
    dataset: Path,
    sequences: Sequence[str],
    *,
    layout: DatasetLayout,
    version: str | None = None,
    split: str | None = None,
) -> list[str]:
    """The sequences every scan of which has a ground-truth label file (`version` and `split`
    are a tables layout's)."""
    found = discover(
        dataset, sequences, missing_ok=True, layout=layout, version=version, split=split
    ).by_sequence()
    return [s for s, scans in found.items() if scans and all(e.label_path for e in scans)]


def predictions_description(checkpoint_sha256: str | None, profile: DatasetProfile) -> str:
    """The predictions zip's description.txt: the leaderboard's default lines, then the run's."""
    return description_text(
        LeaderboardEntry(),
        written_by="the rangeret gateway",
        checkpoint_sha256=checkpoint_sha256,
        profile=profile.name,
    )


def write_predictions_zip(
    pred_root: Path,
    entries: Sequence[ScanEntry],
    sequences: Sequence[str],
    path: Path,
    description: str,
    *,
    profile: DatasetProfile,
    workers: int | None = None,
    sha256: str | None = None,
) -> None:
    """The job's predictions as a reproducible zip with explicit directory entries, as
    `sequences/<id as on disk>/predictions/NNNNNN.label` for every folder layout; a tables
    layout's is nuScenes' results folder (`write_nuscenes_results`: each split folder of the
    predictions with its `submission.json`, naming the checkpoint's `sha256`).

    When the profile is the benchmark's (SemanticKITTI) and all the sequences are its test sequences, the archive
    holds the directory entries of every test sequence, as the benchmark server wants, so it
    passes the submission validator. The labels are read and deflated in `workers` threads
    (default: every CPU this process may use); the archive's bytes do not depend on it.
    """
    if profile.layout.kind == "tables":
        submission = submission_json(SubmissionMeta(), LeaderboardEntry(), sha256)
        write_nuscenes_results(
            pred_root,
            entries,
            path,
            profile=profile,
            submission=submission,
            description=description,
            workers=workers,
        )
        return
    names = list(dict.fromkeys(sequences))
    benchmark = profile.name == BENCHMARK_PROFILE
    if benchmark and all(s in TEST_SEQUENCES for s in names):
        directories = list(required_directories())
    else:
        directories = ["sequences/"]
        for seq in sorted(names):
            directories += [f"sequences/{seq}/", f"sequences/{seq}/predictions/"]
    with atomic_path(path) as tmp, ReproducibleZip(tmp) as zf:
        for name in directories:
            zf.add_directory(name)
        zf.add_files(
            ((entry.prediction, entry.prediction_in(pred_root).read_bytes) for entry in entries),
            workers,
        )
        zf.add_file("description.txt", description.rstrip("\n") + "\n")


def write_report(
    dataset: Path,
    pred_root: Path,
    labelled: Sequence[str],
    folder: Path,
    *,
    profile: DatasetProfile,
    checkpoint_sha256: str | None,
    precision: str | None,
    backend: str,
    version: str | None = None,
    split: str | None = None,
) -> tuple[Path, dict]:
    """Evaluate the `labelled` sequences' predictions into `folder`'s report and its plots, noting
    the `precision` and inference `backend` the network ran with (`version` and `split` are a
    tables layout's); the report's path and the job's metrics (miou, accuracy, iou by class
    name)."""
    report = evaluate_predictions(
        dataset,
        pred_root,
        list(labelled),
        checkpoint_sha256=checkpoint_sha256,
        profile=profile,
        version=version,
        split=split,
    )
    report.precision = precision
    report.backend = backend
    path = folder / REPORT_JSON
    report.write_json(path)
    write_plots(report, folder / PLOTS_DIR, config=profile.labels)
    metrics = {"miou": report.miou, "accuracy": report.accuracy, "iou": report.iou_by_name()}
    return path, metrics


def report_plots(record: JobRecord) -> list[str]:
    """The names of a succeeded labelled job's report PNGs (none for other jobs)."""
    if record.state is not JobState.succeeded or not record.report:
        return []
    folder = Path(record.report).parent / PLOTS_DIR
    try:
        return sorted(p.name for p in folder.iterdir() if PLOT_NAME.fullmatch(p.name))
    except OSError:
        return []


def plot_path(record: JobRecord, name: str) -> Path | None:
    """The file of the job's report PNG `name`; None when the job has no such plot."""
    if name not in report_plots(record):
        return None
    return Path(record.report).parent / PLOTS_DIR / name
