"""Time to write a submission archive with one worker and with every CPU, over synthetic labels.

Run by hand: `python benchmarks/bench_submission.py [--files 2000] [--points 120000] [--rounds 3]`.
Writes `--files` label files of `--points` uint32 labels (runs of raw ids, compressible like real
predictions) with empty sparse scans of the same point counts, then times, in interleaved rounds,
the archive alone (`ReproducibleZip.add_files`, as the gateway's job archives) and the whole
`write_submission` (read, check, deflate, write, then validate), with workers = 1 and workers =
every CPU. Prints medians, label MB/s and the speed-up, and checks the archives are identical.
Needs about `files * points * 4` bytes of disk twice over; timings need the cores to themselves.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from rangeret.dataset.labels import semantickitti
from rangeret.dataset.layout import KITTI_LAYOUT, prediction_path, velodyne_dir
from rangeret.io.atomic import atomic_path
from rangeret.io.scans import LABEL_BYTES, write_labels
from rangeret.io.zipfiles import ReproducibleZip, available_cpus
from rangeret.submission.archives import write_submission

SEQUENCE = "11"
POINT_BYTES = 16


def synthetic_labels(rng: np.random.Generator, points: int, ids: np.ndarray) -> np.ndarray:
    """Runs of 1 to 40 equal raw ids (predictions deflate about 25 to 1), some with instance bits."""
    lengths = rng.integers(1, 41, size=points // 5 + 1)  # about 4 x the runs needed
    values = rng.choice(ids, size=len(lengths)) | (rng.integers(0, 4, len(lengths)) << 16)
    return np.repeat(values.astype(np.uint32), lengths)[:points]


def make_inputs(root: Path, files: int, points: int) -> tuple[Path, Path]:
    """A dataset of sparse scans and a predictions tree of `files` label files."""
    data, preds = root / "data", root / "pred"
    velodyne_dir(data, SEQUENCE, layout=KITTI_LAYOUT).mkdir(parents=True)
    rng = np.random.default_rng(0)
    ids = np.array(sorted(semantickitti().valid_prediction_ids), dtype=np.uint32)
    for i in range(files):
        with open(velodyne_dir(data, SEQUENCE, layout=KITTI_LAYOUT) / f"{i:06d}.bin", "wb") as f:
            f.truncate(points * POINT_BYTES)
        labels = synthetic_labels(rng, points, ids)
        write_labels(prediction_path(preds, SEQUENCE, f"{i:06d}"), labels)
    return data, preds


def archive_only(preds: Path, out: Path, files: int, workers: int) -> None:
    """The labels zipped as the gateway zips a job's predictions."""
    names = [f"{i:06d}" for i in range(files)]
    with atomic_path(out) as tmp, ReproducibleZip(tmp) as zf:
        zf.add_files(
            (
                (
                    f"sequences/{SEQUENCE}/predictions/{name}.label",
                    prediction_path(preds, SEQUENCE, name).read_bytes,
                )
                for name in names
            ),
            workers,
        )


def timed(fn: Callable[[], object]) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--files", type=int, default=2000)
    parser.add_argument("--points", type=int, default=120_000)
    parser.add_argument("--rounds", type=int, default=3, help="interleaved repetitions")
    args = parser.parse_args()
    cpus = available_cpus()
    counts = [1, cpus] if cpus > 1 else [1]
    megabytes = args.files * args.points * LABEL_BYTES / 1e6
    with tempfile.TemporaryDirectory(prefix="bench-submission-") as folder:
        root = Path(folder)
        print(f"writing {args.files:,} label files of {args.points:,} labels ({megabytes:,.0f} MB)")
        data, preds = make_inputs(root, args.files, args.points)
        runs: dict[str, Callable[[Path, int], object]] = {
            "archive": lambda out, w: archive_only(preds, out, args.files, w),
            "write_submission": lambda out, w: write_submission(
                preds, data, out, allow_partial=True, workers=w, labels=semantickitti()
            ),
        }
        times: dict[tuple[str, int], list[float]] = {(k, w): [] for k in runs for w in counts}
        outputs: dict[tuple[str, int], bytes] = {}
        for _ in range(args.rounds):
            for kind, run in runs.items():
                for workers in counts:
                    out = root / f"{kind}-{workers}.zip"
                    times[kind, workers].append(timed(lambda r=run, o=out, w=workers: r(o, w)))
                    outputs[kind, workers] = out.read_bytes()
                    out.unlink()
        size = len(outputs["archive", 1]) / 1e6
        print(f"{cpus} CPU(s); archive {size:,.1f} MB; median of {args.rounds} interleaved rounds:")
        for kind in runs:
            base = statistics.median(times[kind, 1])
            for workers in counts:
                median = statistics.median(times[kind, workers])
                print(
                    f"  {kind:17} workers {workers:3}: {median:7.2f} s  "
                    f"{megabytes / median:7.1f} MB/s of labels  {base / median:5.2f} x"
                )
            same = len({outputs[kind, w] for w in counts}) == 1
            print(f"  {kind:17} archives identical for every worker count: {same}")


if __name__ == "__main__":
    main()
