"""The onnxruntime backend against torch on this CPU: speed at fp32 and label agreement.

For both networks at one resolution (default the semantickitti profile's 64 x 1024) with random
weights of the published layout (8 blocks for rangeret-cir, 4 for rangeret-thesis, or --blocks),
batch 1: the time of exporting and checking the network once, the median network stage of each
backend (interleaved rounds, so that a noisy spell hits both alike) and their ratio, and the
share of the real scan's points whose label (argmax, kNN, raw id) equals torch's.
Run by hand: `python benchmarks/bench_onnx.py [--height 64 --width 1024] [--blocks N]`.
"""

from __future__ import annotations

import argparse
import logging
import os
import statistics
import sys
import tempfile
import time

from _common import REAL_SCAN, require_real_scan

#: Blocks of each network's published layout.
PUBLISHED_BLOCKS = {"rangeret-cir": 8, "rangeret-thesis": 4}

#: The label agreement the onnxruntime backend must reach.
REQUIRED_AGREEMENT = 0.9999


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--height", type=int, default=64)
    parser.add_argument("--width", type=int, default=1024)
    parser.add_argument(
        "--blocks", type=int, help="blocks of both networks (default: 8 and 4, as published)"
    )
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument(
        "--cache",
        metavar="DIR",
        help="keep the exports in DIR/onnx (default: a temporary folder, exported afresh)",
    )
    args = parser.parse_args()
    require_real_scan()
    logging.basicConfig(level=logging.WARNING, format="    %(message)s", stream=sys.stdout)
    logging.getLogger("rangeret.inference.runtime.onnx_backend").setLevel(
        logging.INFO
    )  # the export's check
    with tempfile.TemporaryDirectory() as temporary:
        os.environ["RANGERET_CACHE"] = args.cache or temporary
        run(args)


def run(args: argparse.Namespace) -> None:
    """Export, time and compare both networks; print one block per network."""
    import numpy as np
    import onnxruntime
    import torch

    from rangeret.dataset.profiles import load_profile
    from rangeret.inference.predictor import Predictor
    from rangeret.inference.spec import InferenceSpec
    from rangeret.io.scans import read_scan
    from rangeret.models import build_model

    points = read_scan(REAL_SCAN)
    profile = load_profile().with_overrides(height=args.height, width=args.width)
    print(
        f"real scan ({len(points):,} points) at {args.height} x {args.width}, batch 1, fp32 on the "
        f"CPU, {torch.get_num_threads()} threads; torch {torch.__version__}, onnxruntime "
        f"{onnxruntime.__version__}; medians of {args.rounds} interleaved rounds"
    )
    for name, blocks in PUBLISHED_BLOCKS.items():
        blocks = args.blocks or blocks
        torch.manual_seed(0)
        network = build_model(name, args.height, args.width, layers=blocks)
        fp32 = InferenceSpec(device="cpu", precision="fp32")
        predictors = {"torch": Predictor.from_network(network, profile, fp32)}
        start = time.perf_counter()
        predictors["onnxruntime"] = Predictor.from_network(
            network, profile, fp32.replace(backend="onnxruntime")
        )
        exported = time.perf_counter() - start
        projection = predictors["torch"].project(points)
        labels = {b: p.predict(points).labels for b, p in predictors.items()}
        times: dict[str, list[float]] = {b: [] for b in predictors}
        for _ in range(args.rounds):
            for backend, predictor in predictors.items():
                start = time.perf_counter()
                predictor.logits([projection])
                times[backend].append(time.perf_counter() - start)
        medians = {b: statistics.median(t) for b, t in times.items()}
        agree = float(np.mean(labels["onnxruntime"] == labels["torch"]))
        verdict = "at least" if agree >= REQUIRED_AGREEMENT else "BELOW"
        print(f"  {name} ({blocks} blocks): export and check {exported:.1f} s")
        print(
            f"    torch {1e3 * medians['torch']:8.1f} ms   onnxruntime "
            f"{1e3 * medians['onnxruntime']:8.1f} ms   onnxruntime x"
            f"{medians['torch'] / medians['onnxruntime']:.2f} vs torch"
        )
        print(
            f"    labels equal to torch's on {100 * agree:.3f} % of points "
            f"({verdict} the required {100 * REQUIRED_AGREEMENT:.2f} %)"
        )


if __name__ == "__main__":
    main()
