"""Forward-pass precision on this machine: speed of fp32, bf16 (and fp16) and label agreement.

For both networks at one resolution, on the real scan: the median forward time of each precision
(interleaved rounds, so that a noisy spell hits every precision alike), the speed-up over fp32,
and the share of the scan's points whose label (argmax, kNN, raw id) equals fp32's. The thesis
network runs with random weights; its agreement is measured against its own fp32 labels.
Run by hand: `python benchmarks/bench_precision.py [--height 64 --width 1024] [--fp16]`.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch
from _common import REAL_SCAN, require_real_scan

from rangeret.dataset.profiles import load_profile
from rangeret.inference.predictor import Predictor
from rangeret.inference.spec import InferenceSpec
from rangeret.io.scans import read_scan
from rangeret.models import build_model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--height", type=int, default=64)
    parser.add_argument("--width", type=int, default=1024)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--fp16", action="store_true", help="also fp16 (slow on most CPUs)")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    require_real_scan()
    points = read_scan(REAL_SCAN)
    profile = load_profile().with_overrides(height=args.height, width=args.width)
    precisions = ["fp32", "bf16"] + (["fp16"] if args.fp16 else [])
    print(
        f"real scan ({len(points):,} points) at {args.height} x {args.width}, batch 1, "
        f"{args.device}, {torch.get_num_threads()} torch threads, {args.rounds} rounds"
    )
    for name in ("rangeret-thesis", "rangeret-cir"):
        torch.manual_seed(0)
        network = build_model(name, args.height, args.width)
        predictors = {
            p: Predictor.from_network(
                network, profile, InferenceSpec(device=args.device, precision=p)
            )
            for p in precisions
        }
        projection = predictors["fp32"].project(points)
        labels = {p: pred.predict(points).labels for p, pred in predictors.items()}
        times: dict[str, list[float]] = {p: [] for p in precisions}
        for _ in range(args.rounds):
            for p, pred in predictors.items():
                start = time.perf_counter()
                pred.logits([projection])
                times[p].append(time.perf_counter() - start)
        base = statistics.median(times["fp32"])
        for p in precisions:
            median = statistics.median(times[p])
            agree = float(np.mean(labels[p] == labels["fp32"]))
            print(
                f"  {name:16s} {p}: {1e3 * median:8.1f} ms  x{base / median:4.2f} vs fp32  "
                f"labels equal to fp32 on {100 * agree:6.2f} % of points"
            )


if __name__ == "__main__":
    main()
