"""Forward-pass precision and graph on this machine: the network as it is against its inference
graph, each in fp32 and bf16, with label agreement.

For both networks at each resolution, on the real scan: the median forward time of each variant
(interleaved rounds, so that a noisy spell hits every variant alike), its speed-up over the plain
fp32 network and over the fast fp32 graph, and the share of the scan's points whose label (argmax,
kNN, raw id) equals plain fp32's. `plain` is the network as it is (bf16 under autocast, as before
the graph); `fast` is the Predictor's inference graph (`rangeret.inference.runtime.fast_graph`),
whose one-time build is timed too; with --compile, `compiled` is that graph under torch.compile,
whose one-time compilation is timed. The thesis network runs with random weights; its agreement is
measured against its own fp32 labels.
Run by hand: `python benchmarks/bench_precision.py [--sizes 64x1024 64x512] [--threads N]
[--compile] [--fp16]`. On a CPU with AMX, `ONEDNN_MAX_CPU_ISA=AVX512_CORE_BF16` in the environment
holds oneDNN to AVX-512 bf16, a stand-in for a CPU without AMX (docs/speed.md).
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
from rangeret.inference.runtime.fast_graph import DTYPES, build_fast_graph
from rangeret.inference.spec import InferenceSpec
from rangeret.io.scans import read_scan
from rangeret.models import build_model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", nargs="+", default=["64x1024", "64x512"], help="HxW each")
    parser.add_argument("--models", nargs="+", default=["rangeret-thesis", "rangeret-cir"])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--fp16", action="store_true", help="also plain fp16 (slow on most CPUs)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, help="torch threads (default: torch's own)")
    parser.add_argument(
        "--compile", action="store_true", help="also the graph under torch.compile (inductor)"
    )
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    require_real_scan()
    points = read_scan(REAL_SCAN)
    variants = [("plain", "fp32"), ("plain", "bf16"), ("fast", "fp32"), ("fast", "bf16")]
    variants += [("plain", "fp16")] if args.fp16 else []
    variants += [("compiled", "fp32"), ("compiled", "bf16")] if args.compile else []
    for size in args.sizes:
        height, width = (int(v) for v in size.split("x"))
        profile = load_profile().with_overrides(height=height, width=width)
        print(
            f"real scan ({len(points):,} points) at {height} x {width}, batch 1, {args.device}, "
            f"{torch.get_num_threads()} torch threads, {args.rounds} rounds"
        )
        for name in args.models:
            torch.manual_seed(0)
            network = build_model(name, height, width)
            run(name, network, profile, variants, points, args)


def run(name, network, profile, variants, points, args) -> None:
    """Time and compare every variant of one network at one resolution, and print a line each."""
    predictors = {}
    for graph, precision in variants:
        predictor = Predictor.from_network(
            network, profile, InferenceSpec(device=args.device, precision=precision)
        )
        if graph == "plain":
            predictor.graph = None
        if graph == "compiled":
            predictor.graph = compiled(name, network, precision, profile, predictor)
        predictors[graph, precision] = predictor
    for precision in ("fp32", "bf16"):
        start = time.perf_counter()
        build_fast_graph(network.eval(), DTYPES[precision])
        print(
            f"  {name:16s} fast {precision} graph built in {1e3 * (time.perf_counter() - start):.0f} ms"
        )
    projection = predictors["plain", "fp32"].project(points)
    labels = {v: p.predict(points).labels for v, p in predictors.items()}
    times: dict[tuple[str, str], list[float]] = {v: [] for v in variants}
    for _ in range(args.rounds):
        for v, predictor in predictors.items():
            start = time.perf_counter()
            predictor.logits([projection])
            times[v].append(time.perf_counter() - start)
    medians = {v: statistics.median(t) for v, t in times.items()}
    plain, fast = medians["plain", "fp32"], medians["fast", "fp32"]
    for (graph, precision), median in medians.items():
        agree = float(np.mean(labels[graph, precision] == labels["plain", "fp32"]))
        print(
            f"  {name:16s} {graph:5s} {precision}: {1e3 * median:8.1f} ms  "
            f"x{plain / median:4.2f} vs plain fp32  x{fast / median:4.2f} vs fast fp32  "
            f"labels equal to plain fp32 on {100 * agree:7.3f} % of points"
        )


def compiled(name, network, precision, profile, predictor) -> torch.nn.Module:
    """The graph in plain operations under torch.compile, whose inductor kernels then fuse the
    pointwise steps themselves; compiled for the profile's resolution by one timed pass."""
    graph = torch.compile(build_fast_graph(network, DTYPES[precision], fused=False), dynamic=False)
    batch = torch.zeros(1, 5, profile.projection.height, profile.projection.width)
    start = time.perf_counter()
    with torch.inference_mode():
        graph(batch.to(predictor.device))
    print(
        f"  {name:16s} compiled {precision} graph: first pass {time.perf_counter() - start:.1f} s"
    )
    return graph


if __name__ == "__main__":
    main()
