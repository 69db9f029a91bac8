"""`rangeret export`: a network as ONNX with the metadata a consumer needs, checked against torch."""

from __future__ import annotations

import argparse
from pathlib import Path

from rangeret.commands import CommandError
from rangeret.inference.spec import InferenceSpec
from rangeret.options import add_weights_options
from rangeret.plugins import Subcommand


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--format", default="onnx", choices=["onnx"], help="the file format (default onnx)"
    )
    p.add_argument("--out", type=Path, required=True, metavar="FILE.onnx", help="file to write")
    p.add_argument(
        "--dynamic-batch",
        action="store_true",
        help="a dynamic batch dimension (default: batch 1)",
    )
    p.add_argument(
        "--check-scan",
        type=Path,
        metavar="FILE",
        help="a .bin scan of the profile's sensor for the check against torch (default: a "
        "simulated street scan), beside fixed-seed noise",
    )
    add_weights_options(p.add_argument_group("network"))


def run(args: argparse.Namespace) -> int:
    """Export a network to ONNX with the metadata a consumer needs, checked against torch."""
    from rangeret.inference.predictor import Predictor
    from rangeret.inference.runtime.onnx_export import ExportError, write_export
    from rangeret.io.scans import read_scan

    spec = InferenceSpec.from_args(args).replace(device="cpu", precision="fp32")
    predictor = Predictor.from_spec(spec)
    profile, config = predictor.profile, predictor.network.config
    scan = read_scan(args.check_scan, profile.points) if args.check_scan else None
    try:
        check = write_export(
            predictor.network,
            profile,
            args.out,
            dynamic_batch=args.dynamic_batch,
            checkpoint_sha256=predictor.checkpoint_sha256,
            scan=scan,
        )
    except ExportError as exc:
        raise CommandError(str(exc)) from exc
    print(check.text())
    print(
        f"{args.out}: {config.name} ({config.layers} blocks), {profile.name} profile, "
        f"({'N' if args.dynamic_batch else 1}, 5, {profile.projection.height}, "
        f"{profile.projection.width}) -> logits, checkpoint sha256 "
        f"{(predictor.checkpoint_sha256 or '')[:12]}"
    )
    return 0


COMMAND = Subcommand(
    "export",
    "a network as ONNX with its metadata, checked against torch",
    add_arguments,
    run,
    extra="onnx",
)
