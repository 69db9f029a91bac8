"""Predicting a whole dataset tree in one process: resumable, atomic, and no scan lost.

Every scan of the chosen sequences ends with exactly one complete prediction file, or is named as
failed with its error. A scan whose prediction already exists with the right size is skipped, so
an interrupted run picks up where it stopped. Reading and projection of the next batch overlap
with the network on the current one.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

from rangeret.dataset.layout import (
    ScanEntry,
    confidence_path,
    is_complete,
    list_scans,
    prediction_path,
)
from rangeret.inference.loading import load_batch
from rangeret.inference.predictor import Predictor
from rangeret.inference.runtime.backends import RuntimeChoiceError
from rangeret.inference.timing import StageTimes
from rangeret.io.run_info import write_run_info
from rangeret.io.scans import (
    write_confidence,
    write_labels,
)

log = logging.getLogger(__name__)


@dataclass
class PredictSummary:
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
        return not self.failed

    def text(self) -> str:
        """A readable summary: counts, throughput, time per stage, then every failed scan."""
        rate = self.written / self.seconds if self.seconds else 0.0
        lines = [
            f"{self.total} scans: {self.written} written, {self.skipped} already done, "
            f"{len(self.failed)} failed; {self.points:,} points in {self.seconds:.1f} s "
            f"({rate:.2f} scans/s)"
        ]
        stages = self.times.per_scan_ms()
        if stages:
            lines.append("per scan: " + ", ".join(f"{k} {v:.1f} ms" for k, v in stages.items()))
        for key, reason in self.failed.items():
            lines.append(f"FAILED {key}: {reason}")
        return "\n".join(lines)


def _batches(entries: Sequence[ScanEntry], size: int) -> Iterator[list[ScanEntry]]:
    for start in range(0, len(entries), size):
        yield list(entries[start : start + size])


def predict_tree(
    predictor: Predictor,
    dataset: Path | str,
    sequences: Sequence[str],
    out: Path | str,
    batch_size: int = 1,
    progress: bool = True,
    on_progress: Callable[[int, int, int], None] | None = None,
    cancel: threading.Event | None = None,
    save_confidence: bool = False,
    read_roots: Sequence[str] | None = None,
) -> PredictSummary:
    """Write `OUT/sequences/XX/predictions/NNNNNN.label` for every scan of `sequences` (and, with
    `save_confidence`, each point's confidence in `OUT/sequences/XX/confidence/NNNNNN.npy`).

    `on_progress(done, failed, total)` is called after every batch; setting `cancel` stops the
    run after the current batch (files already written stay complete). With `read_roots`, a scan
    file that leads outside those folders when it is read is that scan's failure.
    """
    if batch_size < 1:
        raise RuntimeChoiceError(f"--batch-size must be at least 1, got {batch_size}")
    out = Path(out)
    profile = predictor.profile
    entries = list_scans(dataset, sequences, layout=profile.layout)
    summary = PredictSummary(total=len(entries))
    pending = [
        e
        for e in entries
        if not is_complete(e, out, record=profile.points, with_confidence=save_confidence)
    ]
    summary.skipped = len(entries) - len(pending)
    if summary.skipped:
        log.info(
            "%d of %d scans already have predictions; skipping them", summary.skipped, len(entries)
        )
    write_run_info(
        out,
        predictor.describe(),
        runner="rangeret predict",
        dataset=dataset,
        sequences=sequences,
        batch_size=batch_size,
    )

    times = summary.times
    start = time.perf_counter()
    bar = tqdm(total=len(pending), desc="predict", unit="scan", disable=not progress)
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="rangeret-read") as pool:
        batches = _batches(pending, batch_size)
        config = predictor.projection_config
        future = pool.submit(
            load_batch, next(batches, []), config, times, profile.points, read_roots
        )
        while True:
            loaded = future.result()
            if not loaded or (cancel is not None and cancel.is_set()):
                break
            future = pool.submit(
                load_batch, next(batches, []), config, times, profile.points, read_roots
            )
            results = predictor.label_loaded(loaded, times, with_confidence=save_confidence)
            for scan, (found, error) in zip(loaded, results, strict=True):
                if found is None:
                    summary.failed[scan.entry.key] = error or "not labelled"
                    continue
                entry = scan.entry
                with times.stage("write"):
                    if found.confidence is not None:
                        path = confidence_path(out, entry.sequence, entry.name)
                        write_confidence(path, found.confidence)
                    write_labels(prediction_path(out, entry.sequence, entry.name), found.labels)
                summary.written += 1
                summary.points += scan.projection.num_points
            bar.update(len(loaded))
            bar.set_postfix(failed=len(summary.failed))
            if on_progress is not None:
                on_progress(
                    summary.written + len(summary.failed), len(summary.failed), len(pending)
                )
    bar.close()
    summary.seconds = time.perf_counter() - start
    return summary
