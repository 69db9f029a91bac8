"""Scans/s of the Ray pipeline with 1 and 2 model actors against single-process `rangeret predict`,
on the same cores, over a tree of subsampled copies of the real scan.

Run by hand: `python benchmarks/bench_workers.py [--scans 40] [--rounds 3] [--weights kitti|small]`. `kitti`
uses the release-shaped 8-block network at 64 x 1024 (random weights; about 2-3 s per scan on 2
cores), `small` the 2-block weights of the test vectors at 32 x 256. Prints scans/s and the
pipeline's overhead; not a test.
"""

from __future__ import annotations

import argparse
import logging
import statistics
import tempfile
import time
from pathlib import Path

import torch
from _common import REAL_SCAN, require_real_scan, small_state_dict

from rangeret.dataset.layout import KITTI_LAYOUT, list_scans, velodyne_dir
from rangeret.dataset.selection import DatasetSelection
from rangeret.inference.loaded_weights import load_weights
from rangeret.inference.predictor import Predictor
from rangeret.inference.runner import predict_tree
from rangeret.inference.spec import InferenceSpec
from rangeret.inference.timing import StageTimes
from rangeret.io.scans import KITTI_RECORD, read_scan, write_scan
from rangeret.models import build_model
from workers.pipeline import run_pipeline
from workers.sizing import PipelineOptions

SIZES = {"kitti": (64, 1024), "small": (32, 256)}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--scans", type=int, default=40)
    parser.add_argument("--weights", choices=sorted(SIZES), default="kitti")
    parser.add_argument(
        "--rounds", type=int, default=3, help="interleaved repetitions; medians are printed"
    )
    args = parser.parse_args()
    require_real_scan()
    logging.basicConfig(level=logging.WARNING)
    import ray

    points = read_scan(REAL_SCAN)
    h, w = SIZES[args.weights]
    state = (
        build_model("rangeret-cir", h, w).state_dict()  # the release's 8-block shape
        if args.weights == "kitti"
        else small_state_dict()
    )
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        torch.save(state, tmp / "w.pt")
        for i in range(args.scans):
            write_scan(
                velodyne_dir(tmp / "data", "08", layout=KITTI_LAYOUT) / f"{i:06d}.bin",
                points[i % 7 :: 1 + i % 2],
                record=KITTI_RECORD,
            )
        spec = InferenceSpec(checkpoint=str(tmp / "w.pt"), height=h, width=w, device="cpu")
        entries = list_scans(tmp / "data", ["08"], layout=KITTI_LAYOUT)

        ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
        profile = load_weights(spec).profile
        print(
            f"{args.scans} scans at {h} x {w}, {torch.get_num_threads()} torch threads, {args.rounds} rounds"
        )
        rates: dict[str, list[float]] = {}
        ratios: dict[str, list[float]] = {}
        for r in range(args.rounds):  # interleaved, so that a noisy spell hits every runner alike
            start = time.perf_counter()  # both sides include loading the network, as a command does
            summary = predict_tree(
                Predictor.from_spec(spec),
                DatasetSelection.named(tmp / "data", ["08"], KITTI_LAYOUT),
                tmp / f"single{r}",
                progress=False,
            )
            single = summary.written / (time.perf_counter() - start)
            rates.setdefault("predict", []).append(single)
            print(
                f"  round {r + 1}: rangeret predict           {single:6.3f} scans/s   {_stages(summary.times)}"
            )
            for actors, actor_cpus in ((1, 1.5), (2, 0.75)):
                options = PipelineOptions(
                    actors=actors, actor_cpus=actor_cpus
                )  # 2 x 0.75 is the default here
                start = time.perf_counter()
                run = run_pipeline(spec, profile, entries, tmp / f"ray{actors}-{r}", options)
                rate = run.summary.written / (time.perf_counter() - start)
                name = f"{actors} actor(s) x {actor_cpus:g} CPU"
                rates.setdefault(name, []).append(rate)
                ratios.setdefault(name, []).append(single / rate)
                print(
                    f"  round {r + 1}: Ray, {name:17s} {rate:6.3f} scans/s   {_stages(run.summary.times)}"
                )
        print("medians:")
        print(
            f"  rangeret predict (one process)     {statistics.median(rates['predict']):6.3f} scans/s"
        )
        for name, ratio in ratios.items():
            print(
                f"  Ray pipeline, {name:17s}    {statistics.median(rates[name]):6.3f} scans/s   "
                f"overhead against one process (median of paired rounds): {100 * (statistics.median(ratio) - 1):+.1f} %"
            )
        ray.shutdown()


def _stages(times: StageTimes) -> str:
    """Mean ms per scan of each stage, as each process saw it (contention shows in `network`)."""
    return " ".join(f"{k} {v:.0f}" for k, v in times.per_scan_ms().items()) + " ms/scan"


if __name__ == "__main__":
    main()
