"""`rangeret demo`: evaluation and a submission archive end to end on a small simulated example.

The example dataset is simulated (one labelled validation sequence and one short scan per test
sequence). Its predictions come from a stand-in predictor that corrupts the ground truth, so the
evaluator and the archive writer can be seen working before any network is involved; the test
sequences' ground truth is kept aside, as the benchmark server keeps its own.
"""

from __future__ import annotations

import logging
import shutil
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from rangeret.evaluation import evaluate_predictions
from rangeret.io import read_labels, write_labels
from rangeret.labels import semantickitti
from rangeret.layout import discover, labels_dir, prediction_path
from rangeret.plots import write_plots
from rangeret.sim import SensorConfig, simulate_dataset
from rangeret.submission import TEST_SEQUENCES, validate_submission, write_submission

log = logging.getLogger(__name__)

VALID_SCANS = 8
NOISE = 0.15


def corrupt_predictions(
    dataset: Path, truth_root: Path, pred_root: Path, sequences: list[str], noise: float, seed: int = 0
) -> int:
    """Predictions for the scans of `dataset` equal to the ground truth kept under `truth_root`,
    except for a random share `noise` of points."""
    config = semantickitti()
    rng = np.random.default_rng(seed)
    found = discover(dataset, sequences)
    for entry in found.scans:
        truth = labels_dir(truth_root, entry.sequence) / f"{entry.name}.label"
        classes = config.to_class(read_labels(truth)).astype(np.int64)
        flip = rng.random(classes.size) < noise
        classes[flip] = rng.integers(1, config.num_classes, int(flip.sum()))
        write_labels(prediction_path(pred_root, entry.sequence, entry.name), config.to_raw(classes))
    return len(found.scans)


def run_demo(out: Path | str | None = None, progress: bool = True) -> Path:
    """Simulate the example, predict, evaluate, write and validate an archive; return the folder."""
    out = Path(out) if out else Path(f"rangeret-demo-{time.strftime('%Y%m%d-%H%M%S')}")
    out.mkdir(parents=True, exist_ok=True)
    dataset, hidden, preds = out / "dataset", out / "server-labels", out / "predictions"
    sensor = SensorConfig(beams=64, azimuth_steps=1024)
    sequences = {"08": VALID_SCANS, **{s: 1 for s in TEST_SEQUENCES}}

    started = time.perf_counter()
    with tqdm(total=1, desc="simulate", disable=not progress) as bar:
        n = simulate_dataset(dataset, sequences, labelled=True, sensor=sensor, seed=0)
        bar.update()
    for seq in TEST_SEQUENCES:  # the benchmark keeps the test labels on its server
        target = labels_dir(hidden, seq)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.rmtree(target, ignore_errors=True)
        shutil.move(labels_dir(dataset, seq), target)
    log.info("simulated %d scans into %s", n, dataset)

    corrupt_predictions(dataset, dataset, preds, ["08"], NOISE)
    corrupt_predictions(dataset, hidden, preds, list(TEST_SEQUENCES), NOISE, seed=1)
    log.warning(
        "the predictions of this example come from a stand-in that corrupts %d %% of the ground "
        "truth, not from a network",
        int(NOISE * 100),
    )

    report = evaluate_predictions(dataset, preds, ["08"], progress=progress)
    report.notes.append("example predictions: ground truth with random labels on a share of points")
    report.write_json(out / "report.json")
    plots = write_plots(report, out / "plots")

    archive = out / "submission.zip"
    write_submission(
        preds,
        dataset,
        archive,
        allow_partial=True,
        description="rangeret demo: simulated scans, stand-in predictions; not a real submission",
        progress=progress,
    )
    check = validate_submission(archive, dataset, allow_partial=True)
    check.raise_for_problems()

    print(report.table())
    print(f"\nDone in {time.perf_counter() - started:.1f} s. Results in {out}/:")
    print(f"  dataset (simulated, SemanticKITTI layout): {dataset}")
    print(f"  predictions tree:                         {preds}")
    print(f"  evaluation report:                        {out / 'report.json'}")
    for p in plots:
        print(f"  plot:                                     {p}")
    print(f"  submission archive (partial, for tests):  {archive}")
    print("\nOn real data:")
    print("  rangeret evaluate --dataset ROOT --predictions PRED --split valid --json report.json --plots plots")
    print("  rangeret submission --predictions PRED --dataset ROOT --out submission.zip")
    print("  rangeret validate-submission submission.zip --dataset ROOT")
    return out
