"""Predicting a whole dataset tree in one process: resumable, atomic, and no scan lost.

Every scan of the chosen sequences ends with exactly one complete prediction file, or is named as
failed with its error. A scan whose prediction already exists with the right size is skipped, so
an interrupted run picks up where it stopped. Reading and projection of the next batch overlap
with the network on the current one.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

from rangeret.inference import Predictor
from rangeret.io import LABEL_BYTES, ScanFormatError, read_scan, scan_num_points, write_labels
from rangeret.layout import DatasetLayoutError, ScanEntry, discover, prediction_path
from rangeret.projection import Projection
from rangeret.timing import StageTimes

log = logging.getLogger(__name__)

RUN_INFO = "run.json"


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


def is_complete(entry: ScanEntry, out: Path) -> bool:
    """Whether the scan's prediction exists with one label per point (a finished earlier run)."""
    pred = prediction_path(out, entry.sequence, entry.name)
    try:
        return pred.stat().st_size == scan_num_points(entry.scan_path) * LABEL_BYTES
    except (OSError, ScanFormatError):
        return False


def list_scans(
    dataset: Path | str, sequences: Sequence[str], missing_ok: bool = False
) -> list[ScanEntry]:
    """The scans of `sequences`, in order; a missing or empty sequence is an error naming it
    unless `missing_ok` (a partial local copy, logged)."""
    found = discover(dataset, sequences, missing_ok=missing_ok)
    if found.problems:
        raise DatasetLayoutError("; ".join(found.problems))
    absent = sorted(set(sequences) - set(found.sequences))
    if absent:
        log.warning("sequences %s are not in %s: predicting the others", ", ".join(absent), dataset)
    return found.scans


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
) -> PredictSummary:
    """Write `OUT/sequences/XX/predictions/NNNNNN.label` for every scan of `sequences`.

    `on_progress(done, failed, total)` is called after every batch; setting `cancel` stops the
    run after the current batch (files already written stay complete).
    """
    if batch_size < 1:
        raise ValueError(f"--batch-size must be at least 1, got {batch_size}")
    out = Path(out)
    entries = list_scans(dataset, sequences)
    summary = PredictSummary(total=len(entries))
    pending = [e for e in entries if not is_complete(e, out)]
    summary.skipped = len(entries) - len(pending)
    if summary.skipped:
        log.info(
            "%d of %d scans already have predictions; skipping them", summary.skipped, len(entries)
        )
    _write_run_info(out, predictor, dataset, sequences, batch_size)

    def load(batch: list[ScanEntry]) -> list[tuple[ScanEntry, Projection | None, str | None]]:
        loaded = []
        for entry in batch:
            try:
                with predictor.times.stage("read"):
                    points = read_scan(entry.scan_path)
            except (ScanFormatError, OSError) as exc:
                loaded.append((entry, None, str(exc)))
                continue
            loaded.append((entry, predictor.project(points), None))
        return loaded

    start = time.perf_counter()
    predictor.times = summary.times  # this run's stage times, fresh
    bar = tqdm(total=len(pending), desc="predict", unit="scan", disable=not progress)
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="rangeret-read") as pool:
        batches = _batches(pending, batch_size)
        future = pool.submit(load, next(batches, []))
        while True:
            loaded = future.result()
            if not loaded or (cancel is not None and cancel.is_set()):
                break
            future = pool.submit(load, next(batches, []))
            for entry, _, error in loaded:
                if error:
                    summary.failed[entry.key] = error
            good = [(e, p) for e, p, err in loaded if err is None]
            if good:
                try:
                    logits = predictor.network([p for _, p in good])
                except RuntimeError as exc:
                    for entry, _ in good:
                        summary.failed[entry.key] = f"the network failed: {exc}"
                    logits = []
                for (entry, proj), scan_logits in zip(good, logits, strict=False):
                    result = predictor.finish(proj, scan_logits)
                    with predictor.times.stage("write"):
                        write_labels(
                            prediction_path(out, entry.sequence, entry.name), result.labels
                        )
                    summary.written += 1
                    summary.points += proj.num_points
            bar.update(len(loaded))
            bar.set_postfix(failed=len(summary.failed))
            if on_progress is not None:
                on_progress(
                    summary.written + len(summary.failed), len(summary.failed), len(pending)
                )
    bar.close()
    summary.seconds = time.perf_counter() - start
    return summary


def _write_run_info(out: Path, predictor: Predictor, dataset, sequences, batch_size: int) -> None:
    """Record how the predictions were made next to them (checkpoint hash, options)."""
    out.mkdir(parents=True, exist_ok=True)
    info = predictor.describe() | {
        "dataset": str(dataset),
        "sequences": list(sequences),
        "batch_size": batch_size,
        "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    (out / RUN_INFO).write_text(json.dumps(info, indent=2) + "\n")
