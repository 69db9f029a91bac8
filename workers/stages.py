"""The pipeline's CPU stages: read + project before the network, write + count after it.

They run in small Ray Data actor pools beside the model actors. This module imports only numpy and
the torch-free parts of the library, so a reader or writer process starts in about a second and
holds no copy of torch.
Rows carry scans as JSON records, projections and labels as pickles, stage times as JSON.
"""

from __future__ import annotations

import json
import pickle
from collections.abc import Sequence
from pathlib import Path

from rangeret.io import ScanFormatError, read_labels, read_scan, write_labels
from rangeret.labels import LabelConfig
from rangeret.layout import ScanEntry, prediction_path
from rangeret.metrics import RawLabelEvaluator
from rangeret.projection import ProjectionConfig, project_with
from rangeret.timing import StageTimes


def entry_record(entry: ScanEntry) -> list:
    """A scan as a JSON-able record (sequence, name, scan path, label path or None)."""
    return [
        entry.sequence,
        entry.name,
        str(entry.scan_path),
        str(entry.label_path) if entry.label_path else None,
    ]


def entry_from(record: Sequence) -> ScanEntry:
    """The scan of an `entry_record`."""
    seq, name, scan, label = record
    return ScanEntry(seq, name, Path(scan), Path(label) if label else None)


def read_and_project(row: dict, projection: ProjectionConfig) -> dict:
    """Stage 1: read and project every scan of a batch; unreadable scans become named failures."""
    times = StageTimes()
    items = []
    for record in json.loads(row["entries"]):
        entry = entry_from(record)
        try:
            with times.stage("read"):
                points = read_scan(entry.scan_path)
        except (ScanFormatError, OSError) as exc:
            items.append((None, str(exc)))
            continue
        with times.stage("project"):
            items.append((project_with(points, projection), None))
    return {
        "batch": row["batch"],
        "entries": row["entries"],
        "payload": pickle.dumps(items, protocol=pickle.HIGHEST_PROTOCOL),
        "times": times.to_json(),
    }


def write_results(row: dict, out: str, label_config: LabelConfig) -> dict:
    """Stage 3: atomic label writes, and the confusion counts of the batch's labelled scans."""
    evaluator = RawLabelEvaluator(label_config)
    times = StageTimes.from_json(row["times"])
    status = []
    points = 0
    for record, (labels, error) in zip(
        json.loads(row["entries"]), pickle.loads(row["payload"]), strict=True
    ):
        entry = entry_from(record)
        if error is not None:
            status.append(error)
            continue
        try:
            with times.stage("write"):
                write_labels(prediction_path(out, entry.sequence, entry.name), labels)
            if entry.label_path is not None:
                evaluator.add(labels, read_labels(entry.label_path, num_points=labels.size))
        except (OSError, ScanFormatError) as exc:
            status.append(str(exc))
            continue
        points += int(labels.size)
        status.append(None)
    return {
        "batch": row["batch"],
        "entries": row["entries"],
        "status": json.dumps(status),
        "points": points,
        "counts": pickle.dumps(evaluator, protocol=pickle.HIGHEST_PROTOCOL),
        "times": times.to_json(),
        "worker": row["worker"],
    }


class Reader:
    """`read_and_project` as a long-lived Ray Data actor: no worker process start per batch."""

    def __init__(self, projection: ProjectionConfig) -> None:
        self.projection = projection

    def __call__(self, row: dict) -> dict:
        return read_and_project(row, self.projection)


class Writer:
    """`write_results` as a long-lived Ray Data actor."""

    def __init__(self, out: str, label_config: LabelConfig) -> None:
        self.out = out
        self.label_config = label_config

    def __call__(self, row: dict) -> dict:
        return write_results(row, self.out, self.label_config)
