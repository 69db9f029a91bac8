"""Per-scan input and output time on the real 123,389-point scan: reading the `.bin` file,
projecting it, writing its `.label` file (target: at most 10 ms together on 2 cores).

Run by hand: `python benchmarks/bench_projection.py`. Prints medians of interleaved rounds;
not a test.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from _common import REAL_SCAN, require_real_scan

from rangeret.dataset.projection import project
from rangeret.io.scans import read_scan, write_labels

TARGET_MS = 10.0
SIZES = [(64, 512), (64, 1024), (64, 2048)]
ROUNDS = 31


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--rounds", type=int, default=ROUNDS, help=f"interleaved rounds (default {ROUNDS})"
    )
    rounds = parser.parse_args().rounds
    require_real_scan()
    points = read_scan(REAL_SCAN)
    labels = np.zeros(len(points), dtype=np.uint32)
    with tempfile.TemporaryDirectory() as folder:
        target = Path(folder) / "000000.label"
        steps: dict[str, Callable[[], object]] = {
            "read": lambda: read_scan(REAL_SCAN),
            "write": lambda: write_labels(target, labels),
        }
        for h, w in SIZES:
            steps[f"{h}x{w}"] = lambda h=h, w=w: project(points, h, w)
        times = interleaved(steps, rounds)
    print(f"one scan ({len(points):,} points), medians of {rounds} interleaved rounds:")
    for h, w in SIZES:
        filled = project(points, h, w).mask.sum()
        print(
            f"  projection {h} x {w:<5} {1e3 * times[f'{h}x{w}']:6.2f} ms   {filled:>6,} pixels "
            f"filled ({100 * filled / (h * w):4.1f} %)"
        )
    print(f"  reading the .bin file    {1e3 * times['read']:6.2f} ms")
    print(f"  writing the .label file  {1e3 * times['write']:6.2f} ms")
    total = 1e3 * (times["read"] + times["64x1024"] + times["write"])
    print(
        f"  read + project 64 x 1024 + write: {total:.2f} ms, "
        f"{TARGET_MS / total:.1f}x under the {TARGET_MS:.0f} ms target"
    )


def interleaved(steps: dict[str, Callable[[], object]], rounds: int) -> dict[str, float]:
    """Median seconds of each step over `rounds` rounds that run every step once, in turn."""
    for step in steps.values():
        step()
    samples: dict[str, list[float]] = {name: [] for name in steps}
    for _ in range(rounds):
        for name, step in steps.items():
            start = time.perf_counter()
            step()
            samples[name].append(time.perf_counter() - start)
    return {name: statistics.median(values) for name, values in samples.items()}


if __name__ == "__main__":
    main()
