"""INT8 on this CPU: onnxruntime's static quantisation (QDQ) against fp32 and bf16, and its labels.

For the CiR network with random weights of the published layout (8 blocks), at one resolution
(default 64 x 512), batch 1: the fp32 export quantised by `onnxruntime.quantization.quantize_static`
in QDQ format (per-channel weights, int8 activations), calibrated on the real scan turned about
its vertical axis by `--calibration` angles (never the unturned scan, which is the one measured).
Then the median forward pass of torch fp32, torch bf16 (the inference graph `--precision bf16`
runs), onnxruntime fp32 and onnxruntime int8 in interleaved rounds, their ratios against the best
of torch fp32 and bf16, and the share of the real scan's labels (argmax, kNN, raw id) equal to
torch fp32's. INT8 earns a place only where it is faster than that best at >= 99 % agreement.
Run by hand: `python benchmarks/bench_int8.py [--height 64 --width 512] [--rounds 7]`.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from _common import REAL_SCAN, require_real_scan

#: Label agreement with torch fp32 that INT8 must reach.
REQUIRED_AGREEMENT = 0.99


def turned(points: np.ndarray, angle: float) -> np.ndarray:
    """The scan turned by `angle` radians about the sensor's vertical axis."""
    c, s = np.cos(angle), np.sin(angle)
    out = points.copy()
    out[:, 0] = c * points[:, 0] - s * points[:, 1]
    out[:, 1] = s * points[:, 0] + c * points[:, 1]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--height", type=int, default=64)
    parser.add_argument("--width", type=int, default=512)
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--calibration", type=int, default=8, help="turned scans to calibrate on")
    parser.add_argument(
        "--ops",
        default="",
        help="comma-separated ONNX op types to quantise (default: all that onnxruntime can)",
    )
    parser.add_argument(
        "--unsigned", action="store_true", help="uint8 activations with a zero point"
    )
    args = parser.parse_args()
    require_real_scan()
    with tempfile.TemporaryDirectory() as folder:
        run(args, Path(folder))


def run(args: argparse.Namespace, folder: Path) -> None:
    """Export, quantise, time and compare; print one line per configuration."""
    import logging

    logging.getLogger().setLevel(logging.ERROR)  # the quantiser warns once per rank-1 weight
    import onnxruntime
    from onnxruntime.quantization import (
        CalibrationDataReader,
        QuantFormat,
        QuantType,
        quantize_static,
    )
    from onnxruntime.quantization.shape_inference import quant_pre_process

    from rangeret.dataset.profiles import load_profile
    from rangeret.inference.predictor import Predictor
    from rangeret.inference.runtime.onnx_export import INPUT_NAME, OUTPUT_NAME, export_onnx
    from rangeret.inference.spec import InferenceSpec
    from rangeret.io.scans import read_scan
    from rangeret.models import build_model

    points = read_scan(REAL_SCAN)
    profile = load_profile().with_overrides(height=args.height, width=args.width)
    torch.manual_seed(0)
    network = build_model("rangeret-cir", args.height, args.width, layers=8).eval()
    spec = InferenceSpec(device="cpu", precision="fp32")
    fp32 = Predictor.from_network(network, profile, spec)
    bf16 = Predictor.from_network(network, profile, spec.replace(precision="bf16"))

    start = time.perf_counter()
    exported = folder / "fp32.onnx"
    exported.write_bytes(export_onnx(network, profile, dynamic_batch=False, checkpoint_sha256=None))
    prepared = folder / "prepared.onnx"
    quant_pre_process(str(exported), str(prepared), skip_symbolic_shape=True)
    angles = np.linspace(0, 2 * np.pi, args.calibration, endpoint=False) + np.pi / args.calibration
    images = [fp32.project(turned(points, a)).image[None] for a in angles]

    class Reader(CalibrationDataReader):
        """The turned scans' range images, one batch each."""

        def __init__(self) -> None:
            self.left = iter(images)

        def get_next(self) -> dict[str, np.ndarray] | None:
            image = next(self.left, None)
            return None if image is None else {INPUT_NAME: image}

    quantised = folder / "int8.onnx"
    quantize_static(
        str(prepared),
        str(quantised),
        Reader(),
        quant_format=QuantFormat.QDQ,
        per_channel=True,
        activation_type=QuantType.QUInt8 if args.unsigned else QuantType.QInt8,
        weight_type=QuantType.QInt8,
        op_types_to_quantize=[op for op in args.ops.split(",") if op] or None,
        extra_options={"ActivationSymmetric": not args.unsigned},
    )
    made = time.perf_counter() - start
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = torch.get_num_threads()
    sessions = {
        name: onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        for name, path in (("ort fp32", exported), ("ort int8", quantised))
    }
    projection = fp32.project(points)
    image = projection.image[None]

    def ort(name: str):
        return lambda: torch.from_numpy(sessions[name].run([OUTPUT_NAME], {INPUT_NAME: image})[0])

    runs = {
        "torch fp32": lambda: fp32.logits([projection]),
        "torch bf16": lambda: bf16.logits([projection]),
        "ort fp32": ort("ort fp32"),
        "ort int8": ort("ort int8"),
    }
    labels = {}
    for name, forward in runs.items():
        logits = forward()
        (classes,) = fp32.refine_batch([projection], logits)
        labels[name] = fp32.to_raw(classes)
    times: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(args.rounds):
        for name, forward in runs.items():
            begin = time.perf_counter()
            forward()
            times[name].append(time.perf_counter() - begin)
    medians = {name: statistics.median(t) for name, t in times.items()}
    best = min(medians["torch fp32"], medians["torch bf16"])
    print(
        f"real scan ({len(points):,} points), rangeret-cir 8 blocks at {args.height} x "
        f"{args.width}, batch 1, {torch.get_num_threads()} threads; torch {torch.__version__}, "
        f"onnxruntime {onnxruntime.__version__}; medians of {args.rounds} interleaved rounds"
    )
    quantised_ops = args.ops or "all"
    activations = "uint8" if args.unsigned else "int8 symmetric"
    print(
        f"  export, prepare, calibrate ({args.calibration} turned scans), quantise "
        f"({quantised_ops} ops, {activations} activations): {made:.1f} s"
    )
    for name, median in medians.items():
        agree = float(np.mean(labels[name] == labels["torch fp32"]))
        print(
            f"  {name:10s} {1e3 * median:8.1f} ms   x{best / median:5.2f} vs the best torch   "
            f"labels equal to torch fp32's: {100 * agree:7.3f} %"
        )
    int8_agree = float(np.mean(labels["ort int8"] == labels["torch fp32"]))
    earns = medians["ort int8"] < best and int8_agree >= REQUIRED_AGREEMENT
    print(f"  INT8 {'earns' if earns else 'does not earn'} its place on this CPU")


if __name__ == "__main__":
    sys.exit(main())
