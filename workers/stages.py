"""The pipeline's stages: read + project, the network + kNN (+ objects with panoptic
segmentation; `ModelWorker`), write + count.

The CPU stages run in small Ray Data actor pools beside the model actors. This module imports only
numpy and the torch-free parts of the library (the model stage imports torch when its actor is
built), so a reader or writer process starts in about a second and holds no copy of torch. A batch
travels between stages as one typed `BatchRecord`, encoded into a Ray Data row by `encode` and read
back by `BatchRecord.decode`.
"""

from __future__ import annotations

import logging
import os
import pickle
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from rangeret.dataset.distance import distance_bands
from rangeret.dataset.layout import ScanEntry
from rangeret.dataset.profiles import DatasetProfile
from rangeret.dataset.projection import ProjectionConfig
from rangeret.evaluation.counting import RawLabelEvaluator
from rangeret.evaluation.evaluate import count_scan
from rangeret.inference.loading import LoadedScan, load_batch, predict_loaded
from rangeret.inference.spec import InferenceSpec
from rangeret.inference.timing import StageTimes
from rangeret.inference.writing import write_prediction
from rangeret.io.scans import PointRecord, ScanFormatError

if TYPE_CHECKING:  # torch stays out of the CPU stages' processes
    from rangeret.inference.predictor import Predictor

log = logging.getLogger(__name__)

#: The one column of a pipeline row: the pickled `BatchRecord`.
ROW_COLUMN = "record"


@dataclass
class BatchRecord:
    """One batch of scans on its way through the pipeline.

    The reader fills `loaded` (a projection or a failure per scan) and, for each labelled scan
    it projected, `bands` (each point's distance band, from the projection's ranges; None for the
    other scans); the model actor replaces `loaded` by `results` (what each scan's prediction
    file holds, raw ids or panoptic labels, or a failure per scan) and names itself in `worker`;
    the writer clears `results` and `bands` once the files are written and fills `failures`,
    `points` and `counts`.
    """

    index: int
    entries: list[ScanEntry]
    times: StageTimes = field(default_factory=StageTimes)
    loaded: list[LoadedScan] = field(default_factory=list)
    results: list[tuple[np.ndarray | None, str | None]] = field(default_factory=list)
    bands: list[np.ndarray | None] = field(default_factory=list)
    worker: str = ""
    failures: list[str | None] = field(default_factory=list)
    points: int = 0
    counts: RawLabelEvaluator | None = None

    def encode(self) -> dict:
        """The record as a Ray Data row."""
        return {ROW_COLUMN: pickle.dumps(self, protocol=pickle.HIGHEST_PROTOCOL)}

    @classmethod
    def decode(cls, row: dict) -> BatchRecord:
        """The record of a row made by `encode`."""
        record = pickle.loads(row[ROW_COLUMN])
        if not isinstance(record, cls):
            raise TypeError(f"a pipeline row holds {type(record).__name__}, not a BatchRecord")
        return record


def read_and_project(
    record: BatchRecord,
    projection: ProjectionConfig,
    *,
    points: PointRecord,
    within: Sequence[str] | None = None,
) -> BatchRecord:
    """Stage 1: read and project every scan of a batch; unreadable scans (and, with `within`,
    files that lead outside those folders) become named failures. Labelled scans get their
    points' distance bands from the projection's ranges, so the writer counts them by distance
    without reading the scan again."""
    record.loaded = load_batch(
        record.entries, projection, record.times, record=points, within=within
    )
    record.bands = [
        distance_bands(scan.projection.unproj_range)
        if scan.projection is not None and scan.entry.label_path is not None
        else None
        for scan in record.loaded
    ]
    return record


def write_results(
    record: BatchRecord, out: str, profile: DatasetProfile, panoptic: bool = False
) -> BatchRecord:
    """Stage 3: atomic label writes, and the confusion counts of the batch's labelled scans (by
    sequence and by the distance bands the reader found). With `panoptic` the labels and the
    ground truth are the layout's panoptic labels, and their semantic parts are counted."""
    evaluator = RawLabelEvaluator.for_profile(profile)
    encoding = profile.layout.panoptic_encoding if panoptic else None
    failures: list[str | None] = []
    rows = zip(record.entries, record.results, record.bands, strict=True)
    for entry, (labels, error), bands in rows:
        if error is not None:
            failures.append(error)
            continue
        try:
            with record.times.stage("write"):
                write_prediction(entry, out, labels)
            if entry.label_path is not None:
                gt = entry.label_file.read(entry.label_path, num_points=labels.size)
                if encoding is None:
                    evaluator.add(labels, gt, entry.sequence, bands)
                else:
                    semantic = encoding.semantic
                    evaluator.add(semantic(labels), semantic(gt), entry.sequence, bands)
        except (OSError, ScanFormatError) as exc:
            failures.append(str(exc))
            continue
        record.points += int(labels.size)
        failures.append(None)
    record.failures, record.counts, record.results, record.bands = failures, evaluator, [], []
    return record


def label_batch(predictor: Predictor, encoded: bytes) -> bytes:
    """Stage 2 on one encoded `BatchRecord`: the network, kNN refinement and raw ids of its
    scans, and their objects when the predictor clusters them (`predict_loaded`: what each
    scan's file holds, or a named failure); the record names the device and process that ran
    it."""
    record = BatchRecord.decode({ROW_COLUMN: encoded})
    record.results = [
        (None, found) if isinstance(found, str) else (found.labels, None)
        for found in predict_loaded(predictor, record.loaded, record.times)
    ]
    record.loaded = []
    record.worker = f"{predictor.device}@{os.getpid()}"
    return record.encode()[ROW_COLUMN]


class Reader:
    """`read_and_project` as a long-lived Ray Data actor: no worker process start per batch."""

    def __init__(
        self,
        projection: ProjectionConfig,
        record: PointRecord,
        within: Sequence[str] | None = None,
    ) -> None:
        self.projection = projection
        self.record = record
        self.within = within

    def __call__(self, row: dict) -> dict:
        decoded = BatchRecord.decode(row)
        return read_and_project(
            decoded, self.projection, points=self.record, within=self.within
        ).encode()


class Writer:
    """`write_results` as a long-lived Ray Data actor."""

    def __init__(self, out: str, profile: DatasetProfile, panoptic: bool = False) -> None:
        self.out = out
        self.profile = profile
        self.panoptic = panoptic

    def __call__(self, row: dict) -> dict:
        record = BatchRecord.decode(row)
        return write_results(record, self.out, self.profile, self.panoptic).encode()


class ModelWorker:
    """Stage 2 (an actor): the network on a batch, then kNN refinement, raw ids and, when the
    spec asks for panoptic segmentation, objects. It loads the spec's weights once, for the
    profile the driver settled and from bytes of the SHA-256 the driver checked (when given), and
    warms the network up before it takes a batch, so the first batch's times are those of any
    other."""

    def __init__(
        self,
        spec: InferenceSpec,
        profile: DatasetProfile,
        cpus: float,
        checkpoint_sha256: str | None = None,
    ) -> None:
        from rangeret.inference.loaded_weights import load_checked_weights
        from rangeret.inference.predictor import Predictor
        from rangeret.inference.scan_worker import use_cpus, warm_up

        use_cpus(cpus)
        weights = load_checked_weights(
            spec,
            checkpoint_sha256,
            "a model actor",
            "by the job's driver",
            "run the job again",
            profile=profile,
        )
        self.predictor = Predictor(weights, spec)
        self.warm_up_seconds = warm_up(self.predictor)

    def __call__(self, batch: dict) -> dict:
        return {ROW_COLUMN: [label_batch(self.predictor, row) for row in batch[ROW_COLUMN]]}


def count_labels(
    entries: Iterable[ScanEntry], out: Path | str, profile: DatasetProfile
) -> RawLabelEvaluator:
    """Confusion counts of semantic predictions made earlier (skipped on resume), read from
    their files as `rangeret evaluate` reads them (the scan for its points' distance bands)."""
    evaluator = RawLabelEvaluator.for_profile(profile)
    for entry in entries:
        if entry.label_path is not None:
            count_scan(evaluator, entry, entry.prediction_in(out), profile.points)
    return evaluator
