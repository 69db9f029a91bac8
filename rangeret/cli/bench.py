"""`rangeret bench`: a speed card for this machine, for a checkpoint, a published model or random
weights of a network (`rangeret.inference.speed_inputs` gets them and the scan,
`rangeret.inference.speed_card` measures)."""

from __future__ import annotations

import argparse
from pathlib import Path

from rangeret.inference.network_fields import DEVICES, MODELS
from rangeret.plugins import Subcommand

#: What the card can time.
BENCH_BACKENDS = ("torch", "onnxruntime")
BENCH_PRECISIONS = ("fp32", "bf16", "fp16")


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of `rangeret bench`."""
    from rangeret.inference.speed_card import DEFAULT_ROUNDS
    from rangeret.inference.speed_inputs import DEFAULT_MODEL

    weights = p.add_argument_group("network")
    weights.add_argument(
        "--checkpoint",
        metavar="NAME|FILE",
        help="a checkpoint file or a published model's name, fetched when it is not in the "
        "cache (random weights of its network when it cannot be); default: "
        f"{DEFAULT_MODEL} from the cache, else random weights of its network",
    )
    weights.add_argument(
        "--model",
        choices=MODELS,
        help="without --checkpoint: time this network with random weights",
    )
    weights.add_argument(
        "--random",
        action="store_true",
        help="random weights of the checkpoint's network (the speed is the same; the labels' "
        "agreement is that of random weights)",
    )
    weights.add_argument(
        "--profile",
        metavar="NAME|FILE",
        help="dataset profile (default: the checkpoint's, else semantickitti)",
    )
    weights.add_argument(
        "--height", type=_positive, help="range image rows (default: the profile's)"
    )
    weights.add_argument(
        "--width", type=_positive, help="range image columns (default: the profile's)"
    )
    run = p.add_argument_group("measurement")
    run.add_argument(
        "--device",
        choices=DEVICES,
        default="auto",
        help="where the network runs; auto picks CUDA when present (default: auto)",
    )
    run.add_argument(
        "--backends",
        nargs="+",
        choices=BENCH_BACKENDS,
        default=["torch"],
        help="torch at each precision, onnxruntime at fp32 (needs the onnx extra; its first "
        "export of a full-size network takes minutes) (default: torch)",
    )
    run.add_argument(
        "--precisions",
        nargs="+",
        choices=BENCH_PRECISIONS,
        help="torch precisions to time besides fp32 (default: bf16 where the CPU or GPU runs it "
        "natively, fp16 on CUDA)",
    )
    run.add_argument(
        "--rounds",
        type=_positive,
        default=DEFAULT_ROUNDS,
        metavar="N",
        help=f"timed rounds of each configuration (default: {DEFAULT_ROUNDS})",
    )
    run.add_argument(
        "--scan",
        type=Path,
        metavar="FILE.bin",
        help="the scan to label (in the profile's point record; default: a simulated one)",
    )
    run.add_argument("--threads", type=_positive, metavar="N", help="torch threads")
    run.add_argument("--seed", type=int, default=0, help="of random weights and the simulated scan")
    p.add_argument("--json", action="store_true", help="print the card as JSON")


def run(args: argparse.Namespace) -> int:
    """Measure the speed card and print it as a table, or as JSON with --json."""
    import json

    import torch

    from rangeret.inference.speed_card import measure
    from rangeret.inference.speed_inputs import bench_weights, read_bench_scan, simulated_scan

    if args.threads:
        torch.set_num_threads(args.threads)
    bench = bench_weights(
        args.checkpoint,
        model=args.model,
        profile=args.profile,
        height=args.height,
        width=args.width,
        random=args.random,
        seed=args.seed,
    )
    profile = bench.weights.profile
    if args.scan is not None:
        points, source = read_bench_scan(args.scan, profile), str(args.scan)
    else:
        points, source = simulated_scan(profile, args.seed), "simulated"
    card = measure(
        bench,
        points,
        device=args.device,
        backends=args.backends,
        precisions=args.precisions,
        rounds=args.rounds,
        scan_source=source,
    )
    print(json.dumps(card.to_dict(), indent=2) if args.json else card.text())
    return 0


COMMAND = Subcommand(
    "bench",
    "a speed card for this machine: each precision's and backend's time per scan and agreement",
    add_arguments,
    run,
)
