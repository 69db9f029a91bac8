"""Reading and projecting the scans of a batch, with every unreadable scan kept as a named failure.

The first step of every prediction runner (`rangeret predict` and the Ray pipeline's readers),
written once. Torch-free, so the pipeline's reader processes start without torch.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from rangeret.io import ScanFormatError, read_scan
from rangeret.layout import ScanEntry
from rangeret.projection import Projection, ProjectionConfig, project_with
from rangeret.timing import StageTimes


@dataclass
class LoadedScan:
    """One scan of a batch: its projection, or why it could not be read (exactly one is set)."""

    entry: ScanEntry
    projection: Projection | None = None
    error: str | None = None


def load_batch(
    entries: Sequence[ScanEntry], config: ProjectionConfig, times: StageTimes
) -> list[LoadedScan]:
    """Read and project every scan of `entries`, in order; times go to `times` (read, project)."""
    loaded = []
    for entry in entries:
        try:
            with times.stage("read"):
                points = read_scan(entry.scan_path)
        except (ScanFormatError, OSError) as exc:
            loaded.append(LoadedScan(entry, error=str(exc)))
            continue
        with times.stage("project"):
            loaded.append(LoadedScan(entry, projection=project_with(points, config)))
    return loaded
