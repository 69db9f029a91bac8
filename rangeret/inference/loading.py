"""Batches of scans, read and projected, with every unreadable scan kept as a named failure,
and their labelling with a predictor, a failing network pass naming every scan it held.

The first steps of every prediction runner (`rangeret predict`, the Ray pipeline's readers and
model actors, the GPU check, and for scans already in memory the single-scan workers), written
once. Torch-free, so the pipeline's reader processes start without torch.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, TypeVar

import numpy as np

from rangeret.dataset.layout import ScanEntry
from rangeret.dataset.projection import Projection, ProjectionConfig, project_with
from rangeret.inference.results import ScanOutcome
from rangeret.inference.runtime.backends import RuntimeChoiceError
from rangeret.inference.timing import StageTimes
from rangeret.io.scans import PointRecord, ScanFormatError, read_scan

if TYPE_CHECKING:
    from rangeret.inference.predictor import Predictor

T = TypeVar("T")


def check_batch_size(size: int) -> None:
    """`RuntimeChoiceError` naming `--batch-size` unless `size` is at least 1."""
    if size < 1:
        raise RuntimeChoiceError(f"--batch-size must be at least 1, got {size}")


def batches(items: Sequence[T], size: int) -> list[list[T]]:
    """`items` in consecutive batches of `size` (the last one shorter), in order: every runner
    groups scans this way, so a batch holds the same scans, and gives the same labels, in each."""
    check_batch_size(size)
    return [list(items[start : start + size]) for start in range(0, len(items), size)]


@dataclass
class LoadedScan:
    """One scan of a batch: its projection, or why it could not be read (exactly one is set)."""

    entry: ScanEntry
    projection: Projection | None = None
    error: str | None = None

    @property
    def ready(self) -> Projection | str:
        """What `Predictor.label_projections` takes for the scan: its projection, or why it has
        none."""
        if self.projection is not None:
            return self.projection
        return self.error or "the scan was not read"


def load_batch(
    entries: Sequence[ScanEntry],
    config: ProjectionConfig,
    times: StageTimes,
    *,
    record: PointRecord,
    within: Sequence[str] | None = None,
) -> list[LoadedScan]:
    """Read and project every scan of `entries`, in order; times go to `times` (read, project).

    A file that is not whole records of `record`, whose points cannot be projected (a laser id
    off the image), or that leads outside the folders `within` (when given), becomes a failure
    naming the file.
    """
    loaded = []
    for entry in entries:
        try:
            with times.stage("read"):
                points = read_scan(entry.scan_path, record, within)
        except (ScanFormatError, OSError) as exc:
            loaded.append(LoadedScan(entry, error=str(exc)))
            continue
        try:
            with times.stage("project"):
                projection = project_with(points, config)
        except ValueError as exc:
            loaded.append(LoadedScan(entry, error=str(ScanFormatError(entry.scan_path, str(exc)))))
            continue
        loaded.append(LoadedScan(entry, projection=projection))
    return loaded


def project_scans(
    scans: Sequence[np.ndarray], config: ProjectionConfig, times: StageTimes
) -> list[Projection | str]:
    """Project scans already in memory (a request's points), in order; a scan whose points cannot
    be projected (a laser id off the image) becomes the reason instead."""
    projected: list[Projection | str] = []
    for points in scans:
        try:
            with times.stage("project"):
                projected.append(project_with(points, config))
        except ValueError as exc:
            projected.append(str(exc))
    return projected


def predict_loaded(
    predictor: Predictor,
    scans: Sequence[LoadedScan],
    times: StageTimes | None = None,
    *,
    with_confidence: bool = False,
) -> list[ScanOutcome]:
    """A prediction or the named failure of each scan of a loaded batch, in order, in one
    network pass; when the pass itself fails (out of device memory, say), each readable scan
    becomes that failure instead of stopping the run, so a dataset run loses no scan unnamed."""
    try:
        return predictor.label_projections(
            [s.ready for s in scans], times, with_confidence=with_confidence
        )
    except RuntimeError as exc:
        reason = f"the network failed: {exc}"
        return [s.error or reason for s in scans]
