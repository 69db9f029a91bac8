"""Training speed and memory: both RangeRet networks at 64x1024 on the CPU, batch 1.

Each network runs in a child process of its own, so that its peak resident memory (getrusage's
maxrss) is its own: the child builds the `Trainer` (thesis recipe: augmentation, the three
losses, AdamW + OneCycle, gradient clipping) on a one-scan tree linked to the real scan, then
times `--steps` training steps after one warm-up step. Data time (read, augment, project) and
step time (forward, losses, backward, optimiser) are reported apart; steps/s counts both.
The thesis's Table 5.3 (and 5.6) gives the GPU figures for comparison: the thesis network trained
at 8.8-8.9 it/s with 3.1 GB on an RTX 2080 (8 GB).
Run by hand: `python benchmarks/bench_training.py [--steps N]`.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import REAL_LABELS, REAL_SCAN, require_real_scan

from rangeret.dataset.layout import KITTI_LAYOUT

MODELS = ("rangeret-thesis", "rangeret-cir")
SIZE = (64, 1024)
#: Table 5.3 / 5.6 of the thesis: training iterations per second and memory on an RTX 2080.
THESIS_GPU = {"rangeret-thesis": (8.8, 3.1)}


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, in MiB (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def measure(model: str, steps: int) -> dict:
    """Time `steps` training steps of `model` in this process; returns the figures as a dict."""
    import torch

    from rangeret.dataset.layout import labels_dir, velodyne_dir
    from rangeret.training import TrainConfig, Trainer
    from rangeret.training.data import collate

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "data"
        velodyne_dir(root, "00", layout=KITTI_LAYOUT).mkdir(parents=True)
        labels_dir(root, "00", layout=KITTI_LAYOUT).mkdir(parents=True)
        (velodyne_dir(root, "00", layout=KITTI_LAYOUT) / "000000.bin").symlink_to(REAL_SCAN)
        (labels_dir(root, "00", layout=KITTI_LAYOUT) / "000000.label").symlink_to(REAL_LABELS)
        config = TrainConfig(
            dataset=str(root),
            out=str(Path(tmp) / "out"),
            model=model,
            height=SIZE[0],
            width=SIZE[1],
            train_sequences=("00",),
            val_sequences=(),
            epochs=steps + 1,
            loader_workers=0,
            progress=False,
            device="cpu",
        )
        trainer = Trainer(config)
        baseline = peak_rss_mb()
        data_times, step_times = [], []
        for i in range(steps + 1):
            start = time.perf_counter()
            batch = collate([trainer.train_set[(i, 0)]])
            loaded = time.perf_counter()
            trainer.train_step(batch)
            done = time.perf_counter()
            if i:
                data_times.append(loaded - start)
                step_times.append(done - loaded)
    data, step = statistics.median(data_times), statistics.median(step_times)
    return {
        "model": model,
        "params": sum(p.numel() for p in trainer.model.parameters()),
        "threads": torch.get_num_threads(),
        "data_s": data,
        "step_s": step,
        "steps_per_s": 1.0 / (data + step),
        "peak_mb": peak_rss_mb(),
        "training_mb": peak_rss_mb() - baseline,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--steps", type=int, default=3, help="timed steps per network (median reported)"
    )
    parser.add_argument(
        "--threads", type=int, help="torch CPU threads (default: torch's own choice)"
    )
    parser.add_argument("--one", choices=MODELS, help=argparse.SUPPRESS)
    args = parser.parse_args()
    require_real_scan()
    if args.one:
        if args.threads:
            import torch

            torch.set_num_threads(args.threads)
        print(json.dumps(measure(args.one, args.steps)), flush=True)
        return
    print(
        f"training at {SIZE[0]}x{SIZE[1]}, batch 1, CPU fp32, {args.steps} timed steps after 1 warm-up step"
    )
    print(
        f"{'model':16} {'params':>10} {'threads':>7} {'data s':>7} {'step s':>7} {'steps/s':>8} "
        f"{'peak MiB':>9} {'+train MiB':>10}   thesis GPU (RTX 2080)"
    )
    for model in MODELS:
        child = subprocess.run(
            [sys.executable, __file__, "--one", model, "--steps", str(args.steps)]
            + (["--threads", str(args.threads)] if args.threads else []),
            check=True,
            capture_output=True,
            text=True,
        )
        r = json.loads(child.stdout.strip().splitlines()[-1])
        gpu = THESIS_GPU.get(model)
        reference = (
            f"{gpu[0]} it/s, {gpu[1]} GB ({gpu[0] * (r['data_s'] + r['step_s']):.0f}x faster)"
            if gpu
            else "-"
        )
        print(
            f"{model:16} {r['params']:>10,} {r['threads']:>7} {r['data_s']:>7.3f} {r['step_s']:>7.2f} "
            f"{r['steps_per_s']:>8.3f} {r['peak_mb']:>9.0f} {r['training_mb']:>10.0f}   {reference}",
            flush=True,
        )


if __name__ == "__main__":
    main()
