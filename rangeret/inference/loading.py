"""Reading and projecting the scans of a batch, with every unreadable scan kept as a named failure.

The first step of every prediction runner (`rangeret predict` and the Ray pipeline's readers),
written once. Torch-free, so the pipeline's reader processes start without torch.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from rangeret.dataset.layout import ScanEntry
from rangeret.dataset.projection import Projection, ProjectionConfig, project_with
from rangeret.inference.timing import StageTimes
from rangeret.io.scans import KITTI_RECORD, PointRecord, ScanFormatError, read_scan


@dataclass
class LoadedScan:
    """One scan of a batch: its projection, or why it could not be read (exactly one is set)."""

    entry: ScanEntry
    projection: Projection | None = None
    error: str | None = None


def load_batch(
    entries: Sequence[ScanEntry],
    config: ProjectionConfig,
    times: StageTimes,
    record: PointRecord = KITTI_RECORD,
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
