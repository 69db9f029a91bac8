"""What every runner gives: one `ScanOutcome` per scan (a `ScanPrediction`, or the reason the
scan has none), and the `RunSummary` of a run.

The dataset, files and bag runners, the Ray job (`workers.pipeline`), the Serve replicas, the
gateway and the ROS 2 node all answer in these types, so each reports its scans the same way.
Torch-free, so the Ray driver, the pipeline's CPU stages and the gateway import it without torch.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from rangeret.exceptions import CommandError
from rangeret.inference.timing import StageTimes


@dataclass
class ScanPrediction:
    """The labels of one scan or cloud: what its prediction file holds (uint32, one per point:
    raw ids or classes, and with panoptic segmentation the benchmark's panoptic labels) and,
    when asked, each point's confidence in its label (float32, 0..1), its training classes and
    its object (instance ids unique in the scan, 0 for stuff)."""

    labels: np.ndarray
    #: Each point's softmax probability of its final class at its pixel (float32), when asked.
    confidence: np.ndarray | None = None
    classes: np.ndarray | None = None
    #: Each point's object with panoptic segmentation (uint32, 0 for stuff); None without it.
    instances: np.ndarray | None = None

    @property
    def num_instances(self) -> int:
        """How many objects the scan holds (0 without panoptic segmentation)."""
        if self.instances is None or not self.instances.size:
            return 0
        return int(np.unique(self.instances[self.instances > 0]).size)


#: One scan of a batch: its prediction, or the reason it has none.
ScanOutcome = ScanPrediction | str


@dataclass
class RunSummary:
    """What a run did: scans written, skipped as already done, failed (with reasons), and times."""

    total: int = 0
    written: int = 0
    skipped: int = 0
    points: int = 0
    seconds: float = 0.0
    failed: dict[str, str] = field(default_factory=dict)
    times: StageTimes = field(default_factory=StageTimes)

    @property
    def ok(self) -> bool:
        """True when no scan failed."""
        return not self.failed

    @property
    def done(self) -> int:
        """Scans this run finished, written or failed (the skipped ones not counted)."""
        return self.written + len(self.failed)

    def add(self, key: str, error: str | None, points: int = 0) -> None:
        """Count one scan: written with `points` points when `error` is None, else failed."""
        if error is None:
            self.written += 1
            self.points += points
        else:
            self.failed[key] = error

    def lines(self) -> list[str]:
        """The report: counts, throughput, time per stage, then every failed scan."""
        rate = self.written / self.seconds if self.seconds else 0.0
        lines = [
            f"{self.total} scans: {self.written} written, {self.skipped} already done, "
            f"{len(self.failed)} failed; {self.points:,} points in {self.seconds:.1f} s "
            f"({rate:.2f} scans/s)"
        ]
        stages = self.times.per_scan_ms()
        if stages:
            lines.append("per scan: " + ", ".join(f"{k} {v:.1f} ms" for k, v in stages.items()))
        lines.extend(f"FAILED {key}: {reason}" for key, reason in self.failed.items())
        return lines

    def text(self) -> str:
        """The report as one printable text."""
        return "\n".join(self.lines())

    def raise_failures(self, out: object, *, unit: str = "scan", verb: str = "predicted") -> None:
        """A CommandError naming every failed `unit` when one failed (the others were written
        to `out`): how each runner's command ends a run that lost some of its inputs."""
        if self.failed:
            raise CommandError(
                f"{len(self.failed)} of {self.total} {unit}s could not be {verb} "
                f"(every other {unit} was written to {out})",
                [f"{k}: {v}" for k, v in self.failed.items()],
            )
