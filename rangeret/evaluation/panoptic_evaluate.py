"""Evaluating a tree of panoptic predictions against a dataset's panoptic ground truth.

`rangeret evaluate --panoptic` reads each labelled scan's panoptic ground truth and prediction
(`.label` files of `instance << 16 | raw id`, or nuScenes-panoptic's `.npz` files of
`1000 x class + instance`: the layout's encoding), maps their semantic parts to training classes
as the semantic evaluation does, and counts them under the rules of the profile's panoptic
benchmark (`rangeret.evaluation.panoptic`): the whole label is the instance id, as both official
evaluators take it. Each scan is counted overall, in its sequence, and per distance band (the
band's points alone, segmented and matched among themselves), so the report has the semantic
report's breakdown. As there, anything missing or malformed is listed by file before any number.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from rangeret.dataset.distance import NUM_BANDS, band_limits, band_name, scan_bands
from rangeret.dataset.profiles import DatasetProfile
from rangeret.dataset.selection import DatasetSelection
from rangeret.evaluation.evaluate import EvaluationError, labelled_predictions
from rangeret.evaluation.panoptic import PanopticCounts, PanopticRules
from rangeret.io.scans import ScanFormatError, read_scan

log = logging.getLogger(__name__)


@dataclass
class PanopticReport:
    """The panoptic scores of a predictions tree: overall, per sequence and per distance band,
    each as the official evaluator reports it (`PanopticRules.summarise`)."""

    overall: PanopticCounts
    class_names: tuple[str, ...]
    benchmark: str
    by_sequence: dict[str, PanopticCounts] = field(default_factory=dict)
    by_distance: list[PanopticCounts] = field(default_factory=list)
    num_scans: int = 0
    num_points: int = 0
    profile: str | None = None
    checkpoint_sha256: str | None = None

    @property
    def rules(self) -> PanopticRules:
        """The official evaluator's rules the counts follow."""
        return self.overall.rules

    def summary(self, counts: PanopticCounts | None = None) -> dict[str, Any]:
        """The official output's scores of `counts` (default: overall)."""
        return (counts or self.overall).summary(self.class_names)

    def headline(self) -> dict[str, float]:
        """PQ, SQ, RQ, PQ-dagger and mIoU overall, whatever the benchmark names them."""
        scores = self.overall.scores(self.class_names)
        named = list(scores.evaluated)
        return {
            "pq": scores.mean(scores.pq, named),
            "sq": scores.mean(scores.sq, named),
            "rq": scores.mean(scores.rq, named),
            "pq_dagger": scores.dagger(),
            "miou": scores.mean(scores.iou, named),
        }

    def to_dict(self) -> dict[str, Any]:
        """The JSON report: the official output's keys overall, then the same per sequence and
        per distance band, and what they were computed on."""
        out: dict[str, Any] = {
            "benchmark": self.benchmark,
            "min_points": self.overall.min_points,
            **_plain(self.summary()),
            "num_scans": self.num_scans,
            "num_points": self.num_points,
            "sequences": list(self.by_sequence),
            "per_sequence": {s: _plain(self.summary(c)) for s, c in self.by_sequence.items()},
            "per_distance": [
                dict(
                    zip(("min_m", "max_m"), band_limits(band), strict=True),
                    **_plain(self.summary(c)),
                )
                for band, c in enumerate(self.by_distance)
            ],
        }
        if self.profile:
            out["profile"] = self.profile
        if self.checkpoint_sha256:
            out["checkpoint_sha256"] = self.checkpoint_sha256
        return out

    def write_json(self, path: Path | str) -> None:
        """Write the JSON report, creating its folder."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.to_dict(), indent=2) + "\n")

    def table(self) -> str:
        """Per-class PQ, SQ, RQ and IoU in percent, the means over all, things and stuff, then
        PQ and mIoU per sequence and per distance band."""
        s = self.overall.scores(self.class_names)
        width = max(len(n) for n in (*self.class_names, "PQ-dagger"))
        head = f"{'class':<{width}}  {'PQ %':>6}  {'SQ %':>6}  {'RQ %':>6}  {'IoU %':>6}"
        lines = [head]
        for c in s.evaluated:
            kind = " (thing)" if c in s.things else ""
            lines.append(
                f"{self.class_names[c]:<{width}}  {_pct(s.pq[c])}  {_pct(s.sq[c])}  "
                f"{_pct(s.rq[c])}  {_pct(s.iou[c])}{kind}"
            )
        lines.append("-" * len(head))
        for label, classes in (("all", s.evaluated), ("things", s.things), ("stuff", s.stuff)):
            lines.append(
                f"{label:<{width}}  {_pct(s.mean(s.pq, classes))}  {_pct(s.mean(s.sq, classes))}  "
                f"{_pct(s.mean(s.rq, classes))}  {_pct(s.mean(s.iou, classes))}"
            )
        lines.append(f"{'PQ-dagger':<{width}}  {_pct(s.dagger())}")
        lines.append(
            f"{self.num_scans:,} scans, {self.num_points:,} points; {self.benchmark} rules, "
            f"unmatched segments under {self.overall.min_points} points not counted"
        )
        rows = [
            ("sequence", list(self.by_sequence.items())),
            ("distance", [(band_name(b), c) for b, c in enumerate(self.by_distance)]),
        ]
        for title, parts in rows:
            lines.append("")
            part_width = max(len(title), *(len(name) for name, _ in parts))
            lines.append(f"{title:<{part_width}}  {'PQ %':>6}  {'mIoU %':>6}")
            for name, counts in parts:
                p = counts.scores(self.class_names)
                lines.append(
                    f"{name:<{part_width}}  {_pct(p.mean(p.pq, p.evaluated))}  "
                    f"{_pct(p.mean(p.iou, p.evaluated))}"
                )
        return "\n".join(lines)


def _pct(value: float) -> str:
    return "   n/a" if np.isnan(value) else f"{100 * value:6.2f}"


def _plain(value: Any) -> Any:
    """A summary as JSON-safe data: NaN as None, numpy numbers as Python ones."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (float, np.floating)):
        return None if np.isnan(value) else float(value)
    return value


def panoptic_counter(
    profile: DatasetProfile, rules: PanopticRules, min_points: int | None
) -> PanopticCounts:
    """An empty counter of the profile's classes (its ignored ones, its things) under `rules`."""
    labels = profile.labels
    ignore = [c for c in range(labels.num_classes) if labels.ignored[c]]
    return PanopticCounts(labels.num_classes, ignore, profile.things, rules, min_points)


def evaluate_panoptic(
    selection: DatasetSelection,
    predictions: Path | str,
    *,
    profile: DatasetProfile,
    rules: PanopticRules,
    benchmark: str,
    min_points: int | None = None,
    checkpoint_sha256: str | None = None,
    progress: bool = False,
) -> PanopticReport:
    """Score a tree of panoptic predictions of the `selection` under `rules` (the benchmark
    `benchmark`'s), overall, per sequence and per distance band; `min_points` replaces the rules'
    minimum segment size. An `EvaluationError` lists every missing or malformed file first."""
    if profile.panoptic_refusal() is not None:
        raise EvaluationError([str(profile.panoptic_refusal())])
    selection = selection.for_task(True)
    found, pairs = labelled_predictions(selection, predictions, "panoptic ")
    problems: list[str] = []
    encoding = profile.layout.panoptic_encoding
    report = PanopticReport(
        overall=panoptic_counter(profile, rules, min_points),
        class_names=tuple(profile.labels.class_names),
        benchmark=benchmark,
        by_distance=[panoptic_counter(profile, rules, min_points) for _ in range(NUM_BANDS)],
        profile=profile.name,
        checkpoint_sha256=checkpoint_sha256,
    )
    for seq in found.sequences:
        report.by_sequence[seq] = panoptic_counter(profile, rules, min_points)
    for entry, pred in tqdm(pairs, desc="evaluate", unit="scan", disable=not progress):
        try:
            bands = scan_bands(read_scan(entry.scan_path, record=profile.points))
            truth = entry.label_file.read(entry.label_path, num_points=bands.size)
            predicted = entry.label_file.read(pred, num_points=bands.size)
        except ScanFormatError as exc:
            problems.append(str(exc))
            continue
        gt_class = profile.labels.to_class(encoding.semantic(truth))
        pred_class = profile.prediction_classes(encoding.semantic(predicted))
        arrays = (pred_class, predicted, gt_class, truth)
        report.overall.add(*arrays)
        report.by_sequence[entry.sequence].add(*arrays)
        for band, counts in enumerate(report.by_distance):
            inside = bands == band
            if inside.any():
                counts.add(*(a[inside] for a in arrays))
        report.num_scans += 1
        report.num_points += int(bands.size)
    if problems:
        raise EvaluationError(problems)
    head = report.headline()
    log.info(
        "evaluated %d scans (%d points): PQ %.4f, mIoU %.4f",
        report.num_scans,
        report.num_points,
        head["pq"],
        head["miou"],
    )
    return report
