"""Evaluating a predictions tree against a dataset's ground truth, scan by scan.

Every scan of the chosen sequences must have ground truth and a prediction of the same length;
anything missing or malformed is listed by file before any number is given, so a result is never
computed on a silent subset. Each scan file is read for its points' ranges, which place every
point in a distance band of the report's breakdown. Where every scan has a confidence file
beside its prediction (`rangeret predict --save-confidence`), the report adds the calibration of
those confidences.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from tqdm import tqdm

from rangeret.dataset.distance import scan_bands
from rangeret.dataset.layout import Discovery, ScanEntry
from rangeret.dataset.profiles import DatasetProfile
from rangeret.dataset.selection import DatasetSelection
from rangeret.evaluation.calibration import Calibration
from rangeret.evaluation.counting import RawLabelEvaluator
from rangeret.evaluation.metrics import EvaluationReport
from rangeret.exceptions import DatasetError
from rangeret.io.scans import PointRecord, ScanFormatError, read_confidence, read_scan

log = logging.getLogger(__name__)


class EvaluationError(DatasetError, ValueError):
    """Predictions or ground truth that cannot be evaluated; `problems` names every file."""

    def __init__(self, problems: Sequence[str]) -> None:
        self.problems = list(problems)
        shown = "; ".join(self.problems[:5])
        more = f" (and {len(self.problems) - 5} more)" if len(self.problems) > 5 else ""
        super().__init__(f"{len(self.problems)} problem(s): {shown}{more}")


def count_scan(
    evaluator: RawLabelEvaluator,
    entry: ScanEntry,
    prediction: Path,
    record: PointRecord,
    calibration: Calibration | None = None,
    confidence: Path | None = None,
) -> None:
    """Count one labelled scan's prediction file against its label file, each point in the
    distance band its scan file gives it, and with `calibration` its `confidence` file too;
    `ScanFormatError` names a file that does not fit."""
    if entry.label_path is None:
        raise ValueError(f"scan {entry.key} has no ground-truth label file")
    bands = scan_bands(read_scan(entry.scan_path, record=record))
    gt_raw = entry.label_file.read(entry.label_path, num_points=bands.size)
    pred_raw = entry.label_file.read(prediction, num_points=bands.size)
    refusal = evaluator.refusal(pred_raw)
    if refusal is not None:
        raise ScanFormatError(prediction, refusal)
    evaluator.add(pred_raw, gt_raw, entry.sequence, bands)
    if calibration is not None and confidence is not None:
        config = evaluator.config
        values = read_confidence(confidence, num_points=bands.size)
        gt = config.to_class(gt_raw)
        evaluated = ~np.asarray(config.ignored)[gt]
        correct = evaluator.prediction_classes(pred_raw) == gt
        calibration.add(values[evaluated], correct[evaluated])


def labelled_predictions(
    selection: DatasetSelection, predictions: Path | str, what: str = ""
) -> tuple[Discovery, list[tuple[ScanEntry, Path]]]:
    """The selection's scans and each labelled one's prediction file in the tree `predictions`;
    an `EvaluationError` listing every missing label or prediction file (`what` names the kind
    of prediction, "panoptic " say), or saying that no scan is labelled."""
    found = selection.discover(with_labels=True)
    problems = list(found.problems)
    pairs = []
    for entry in found.scans:
        pred = entry.prediction_in(predictions)
        if not pred.is_file():
            problems.append(f"{pred} is missing (no {what}prediction for scan {entry.key})")
        elif entry.label_path is not None:
            pairs.append((entry, pred))
    if problems:
        raise EvaluationError(problems)
    if not pairs:
        raise EvaluationError(
            [f"no labelled scan found in sequences {', '.join(selection.sequences)}"]
        )
    return found, pairs


def evaluate_predictions(
    selection: DatasetSelection,
    predictions: Path | str,
    *,
    profile: DatasetProfile,
    checkpoint_sha256: str | None = None,
    progress: bool = False,
) -> EvaluationReport:
    """Evaluate a predictions tree against the dataset's labels, overall, per sequence and per
    distance band.

    The profile gives the dataset's layout (and so where each prediction is), point record,
    labels and benchmark rules; `selection` the dataset's scans to evaluate. Raises
    `EvaluationError` listing every missing label or prediction file, every file whose length
    does not match its scan and every prediction the benchmark would refuse.
    """
    found, pairs = labelled_predictions(selection, predictions)
    problems: list[str] = []

    evaluator = RawLabelEvaluator.for_profile(profile)
    confidences = [e.confidence_in(predictions) for e, _ in pairs]
    have = sum(path.is_file() for path in confidences)
    calibration = Calibration() if have == len(pairs) else None
    for (entry, pred), confidence in tqdm(
        list(zip(pairs, confidences, strict=True)),
        desc="evaluate",
        unit="scan",
        disable=not progress,
    ):
        try:
            count_scan(
                evaluator,
                entry,
                pred,
                record=profile.points,
                calibration=calibration,
                confidence=confidence,
            )
        except ScanFormatError as exc:
            problems.append(str(exc))
    if problems:
        raise EvaluationError(problems)
    report = evaluator.report(found.sequences, checkpoint_sha256)
    report.profile = profile.name
    report.calibration = calibration
    if 0 < have < len(pairs):
        report.notes.append(
            f"only {have} of {len(pairs)} scans have confidence files, so no calibration is "
            "reported (rangeret predict --save-confidence writes them for every scan)"
        )
    log.info(
        "evaluated %d scans (%d points): mIoU %.4f",
        report.num_scans,
        report.num_points,
        report.miou,
    )
    return report
