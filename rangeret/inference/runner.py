"""Predicting a whole dataset tree in one process: resumable, atomic, and no scan lost.

Every scan of the chosen sequences ends with exactly one complete prediction file, or is named as
failed with its error. A scan whose prediction already exists with the right size is skipped, so
an interrupted run picks up where it stopped; with `overwrite` every scan is predicted again.
The run is added to the tree's `run.json` before any scan is written, and a tree holding
predictions from other weights is refused unless `overwrite` (`rangeret.io.run_info`). Reading and projection of the next batch overlap
with the network on the current one.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

from tqdm import tqdm

from rangeret.dataset.layout import ScanEntry, is_complete
from rangeret.dataset.selection import DatasetSelection
from rangeret.inference.loading import (
    LoadedScan,
    batches,
    check_batch_size,
    load_batch,
    predict_loaded,
)
from rangeret.inference.predictor import Predictor
from rangeret.inference.results import RunSummary
from rangeret.inference.writing import check_outputs_apart, write_prediction
from rangeret.io.run_info import write_run_info

log = logging.getLogger(__name__)


def predict_tree(
    predictor: Predictor,
    selection: DatasetSelection,
    out: Path | str,
    batch_size: int = 1,
    progress: bool = True,
    on_progress: Callable[[int, int, int], None] | None = None,
    cancel: threading.Event | None = None,
    save_confidence: bool = False,
    read_roots: Sequence[str] | None = None,
    overwrite: bool = False,
    runner: str = "rangeret predict",
    entries: Sequence[ScanEntry] | None = None,
) -> RunSummary:
    """Write a prediction for every scan of the `selection` where the profile's layout puts it
    (`OUT/sequences/XX/predictions/NNNNNN.label`, or nuScenes' `OUT/lidarseg/<split>/`), and with
    `save_confidence` each point's confidence beside it (`OUT/sequences/XX/confidence/`). `entries`,
    when given, are the scans to predict, listed already (a gateway job's); the selection then
    only names the run in `run.json`.

    `on_progress(done, failed, total)` is called after every batch; setting `cancel` stops the
    run after the current batch (files already written stay complete). With `read_roots`, a scan
    file that leads outside those folders when it is read is that scan's failure. With
    `overwrite`, scans already predicted are predicted again and replaced, also when the tree
    holds predictions from other weights; `runner` names the run in `run.json`.
    """
    check_batch_size(batch_size)
    out = Path(out)
    profile = predictor.profile
    if entries is None:
        entries = selection.scans()
    summary = RunSummary(total=len(entries))
    pending = [
        e
        for e in entries
        if overwrite
        or not is_complete(e, out, record=profile.points, with_confidence=save_confidence)
    ]
    check_outputs_apart(pending, out)
    summary.skipped = len(entries) - len(pending)
    if summary.skipped:
        log.info(
            "%d of %d scans already have predictions; skipping them", summary.skipped, len(entries)
        )
    write_run_info(
        out,
        predictor.describe(),
        runner=runner,
        dataset=selection.root,
        sequences=selection.sequences,
        batch_size=batch_size,
        overwrite=overwrite,
    )

    times = summary.times
    start = time.perf_counter()
    bar = tqdm(total=len(pending), desc="predict", unit="scan", disable=not progress)
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="rangeret-read") as pool:
        upcoming = iter(batches(pending, batch_size))
        config = predictor.projection_config

        def read_next() -> Future[list[LoadedScan]]:
            return pool.submit(
                load_batch,
                next(upcoming, []),
                config,
                times,
                record=profile.points,
                within=read_roots,
            )

        future = read_next()
        while True:
            loaded = future.result()
            if not loaded or (cancel is not None and cancel.is_set()):
                break
            future = read_next()
            results = predict_loaded(predictor, loaded, times, with_confidence=save_confidence)
            for scan, found in zip(loaded, results, strict=True):
                entry = scan.entry
                if isinstance(found, str):
                    summary.add(entry.key, found)
                    continue
                with times.stage("write"):
                    write_prediction(entry, out, found.labels, found.confidence)
                summary.add(entry.key, None, scan.projection.num_points)
            bar.update(len(loaded))
            bar.set_postfix(failed=len(summary.failed))
            if on_progress is not None:
                on_progress(summary.done, len(summary.failed), len(pending))
    bar.close()
    summary.seconds = time.perf_counter() - start
    return summary
