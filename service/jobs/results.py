"""A job's result files in its folder: the predictions zip, the evaluation report and its plots.

A job writes `predictions.zip` (as its profile's benchmark zips a job's predictions,
`Benchmark.write_job_zip`: a folder layout's scans as `sequences/XX/predictions/*.label`,
nuScenes' results folder `lidarseg/<split>/` with `<split>/submission.json`; each with a
`description.txt`) and, for the sequences with ground truth, `report.json` and the
report's PNGs under `plots/`, as `rangeret evaluate --plots` draws them. A panoptic job's zip is
its profile's panoptic benchmark's (SemanticKITTI panoptic: the same `.label` tree;
nuScenes-panoptic: `panoptic/<split>/*_panoptic.npz` with `<split>/submission.json`), and its
report the panoptic scores of `rangeret evaluate --panoptic --json` (no PNGs). The routes serve
those files.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Sequence
from pathlib import Path

from rangeret.dataset.layout import ScanEntry
from rangeret.dataset.profiles import DatasetProfile
from rangeret.dataset.selection import DatasetSelection
from rangeret.evaluation.evaluate import evaluate_predictions
from rangeret.evaluation.metrics import ConfusionMatrix
from rangeret.evaluation.panoptic_evaluate import PanopticReport, evaluate_panoptic
from rangeret.evaluation.plots import write_plots
from rangeret.submission.benchmark import JobPredictions
from rangeret.submission.benchmarks import benchmark_of
from rangeret.submission.leaderboard import LeaderboardEntry, description_text
from service.jobs.store import JobRecord
from service.schemas import JobState

PREDICTIONS_ZIP = "predictions.zip"
REPORT_JSON = "report.json"
#: The folder of a labelled job's report PNGs (those of `rangeret evaluate --plots`).
PLOTS_DIR = "plots"
#: A report PNG's name, as `rangeret.evaluation.plots.write_plots` names them.
PLOT_NAME = re.compile(r"^[a-z][a-z-]{0,63}\.png$")


def labelled_sequences(selection: DatasetSelection) -> list[str]:
    """The sequences of the selection every scan of which has a ground-truth label file."""
    found = selection.discover(missing_ok=True).by_sequence()
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
    panoptic: bool = False,
) -> None:
    """The job's predictions as a reproducible zip, as the profile's benchmark (with `panoptic`,
    its panoptic benchmark) zips a job's (`Benchmark.write_job_zip`: SemanticKITTI's test
    sequences with every directory entry the server wants, nuScenes' results folder with
    `submission.json` naming `sha256`). The labels are read and deflated in `workers` threads;
    the archive's bytes do not depend on it."""
    job = JobPredictions(pred_root, entries, sequences, path, description, profile, workers, sha256)
    benchmark_of(profile, panoptic=panoptic).write_job_zip(job)


def write_report(
    selection: DatasetSelection,
    pred_root: Path,
    folder: Path,
    *,
    profile: DatasetProfile,
    checkpoint_sha256: str | None,
    precision: str | None,
    backend: str,
) -> tuple[Path, dict]:
    """Evaluate the predictions of the (labelled) `selection` into `folder`'s report and its
    plots, noting the `precision` and inference `backend` the network ran with; the report's
    path and the job's metrics (miou, accuracy, iou by class name)."""
    report = evaluate_predictions(
        selection, pred_root, checkpoint_sha256=checkpoint_sha256, profile=profile
    )
    report.precision = precision
    report.backend = backend
    path = folder / REPORT_JSON
    report.write_json(path)
    write_plots(report, folder / PLOTS_DIR, config=profile.labels)
    metrics = {"miou": report.miou, "accuracy": report.accuracy, "iou": report.iou_by_name()}
    return path, metrics


def write_panoptic_report(
    selection: DatasetSelection,
    pred_root: Path,
    folder: Path,
    *,
    profile: DatasetProfile,
    checkpoint_sha256: str | None,
    precision: str | None,
    backend: str,
) -> tuple[Path, dict] | None:
    """Score the panoptic predictions of the (labelled) `selection` under the rules of the
    profile's panoptic benchmark into `folder`'s report: `PanopticReport.to_dict()` with the
    task, the headline scores and what the network ran at and with. The report's path and the
    job's metrics (the semantic miou, accuracy and iou of the same points, with pq, sq, rq and
    pq_dagger); None where the profile has no panoptic benchmark to score by."""
    benchmark = benchmark_of(profile, panoptic=True)
    if benchmark.panoptic_rules is None:
        return None
    report = evaluate_panoptic(
        selection,
        pred_root,
        profile=profile,
        rules=benchmark.panoptic_rules,
        benchmark=benchmark.name,
        checkpoint_sha256=checkpoint_sha256,
    )
    path = folder / REPORT_JSON
    body = {
        "task": "panoptic",
        "headline": report.headline(),
        **report.to_dict(),
        "precision": precision,
        "backend": backend,
    }
    path.write_text(json.dumps(body, indent=2) + "\n")
    return path, panoptic_metrics(report, profile)


def panoptic_metrics(report: PanopticReport, profile: DatasetProfile) -> dict:
    """A panoptic job's metrics: the semantic scores of its confusion matrix, as the profile's
    benchmark scores them, and its headline PQ, SQ, RQ and PQ-dagger."""
    confusion = ConfusionMatrix.for_config(config=profile.labels, scoring=profile.benchmark.scoring)
    confusion.merge(report.overall.confusion)
    iou = confusion.iou()
    names = profile.labels.class_names
    head = report.headline()
    miou = confusion.miou()
    return {
        "miou": 0.0 if math.isnan(miou) else float(miou),
        "accuracy": confusion.accuracy(),
        "iou": {names[c]: _number(iou[c]) for c in confusion.include},
        **{key: _number(head[key]) for key in ("pq", "sq", "rq", "pq_dagger")},
    }


def _number(value: float) -> float | None:
    """A score as JSON holds it: NaN (an undefined score) as None."""
    return None if math.isnan(value) else float(value)


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
