"""Scans/s of the Ray pipeline with 1 and 2 model actors against single-process `rangeret predict`,
on the same cores, over a tree of subsampled copies of the real scan.

Run by hand: `python benchmarks/bench_workers.py [--scans 40] [--weights kitti|small]`. `kitti`
uses the release-shaped 8-block network at 64 x 1024 (about 2-3 s per scan on 2 cores), `small`
the 2-block fixture at 32 x 256. Prints scans/s and the pipeline's overhead; not a test.
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
from pathlib import Path

import torch
from _common import REAL_SCAN, SHARED, require_real_scan

from rangeret.inference import PredictorSpec, projection_for
from rangeret.io import read_scan, write_scan
from rangeret.layout import velodyne_dir
from rangeret.models import load_checkpoint
from rangeret.predict import list_scans, predict_tree
from workers.pipeline import PipelineOptions, run_pipeline

SIZES = {"kitti": (64, 1024), "small": (32, 256)}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--scans", type=int, default=40)
    parser.add_argument("--weights", choices=sorted(SIZES), default="kitti")
    args = parser.parse_args()
    require_real_scan()
    logging.basicConfig(level=logging.WARNING)
    import ray

    points = read_scan(REAL_SCAN)
    fixture = torch.load(SHARED / "fixtures" / f"rangeret-cir-{args.weights}.pt", weights_only=False)
    h, w = SIZES[args.weights]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        torch.save(fixture["state_dict"], tmp / "w.pt")
        for i in range(args.scans):
            write_scan(velodyne_dir(tmp / "data", "08") / f"{i:06d}.bin", points[i % 7 :: 1 + i % 2])
        spec = PredictorSpec(checkpoint=str(tmp / "w.pt"), height=h, width=w, device="cpu")
        entries = list_scans(tmp / "data", ["08"])

        predictor = spec.build()
        summary = predict_tree(predictor, tmp / "data", ["08"], tmp / "single", progress=False)
        single = summary.written / summary.seconds
        print(f"{args.scans} scans at {h} x {w}, {torch.get_num_threads()} torch threads")
        print(f"  rangeret predict (one process)        {single:7.3f} scans/s")

        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
        info = load_checkpoint(spec.checkpoint, height=h, width=w).checkpoint_info
        projection = projection_for(info)
        for actors, actor_cpus in ((1, 1.5), (2, 0.75)):
            out = tmp / f"ray{actors}"
            options = PipelineOptions(actors=actors, actor_cpus=actor_cpus, read_cpus=0.25, write_cpus=0.1)
            start = time.perf_counter()
            result = run_pipeline(spec, projection, entries, out, options)
            rate = result.written / (time.perf_counter() - start)
            overhead = 100 * (single / rate - 1)
            print(
                f"  Ray pipeline, {actors} actor(s) x {actor_cpus:g} CPU   {rate:7.3f} scans/s   "
                f"overhead against one process: {overhead:+.1f} %"
            )
        ray.shutdown()


if __name__ == "__main__":
    main()
