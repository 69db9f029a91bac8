"""Network latency per scan: both RangeRet networks at 64x1024 and 64x2048, batch 1.

Prints parameter counts, FLOPs per pass (torch's flop counter), the median forward time on the
CPU (fp32 and bf16 autocast, torch's thread count; 2 on the reference machine) and the fp32
GFLOP/s against the reference machine's matmul peak of about 225 GFLOP/s; on CUDA also fp32 and
fp16-autocast times. Run by hand: `python benchmarks/bench_models.py [--repeat N] [--size 64x1024]`.
"""

from __future__ import annotations

import argparse
import contextlib

import torch
from _common import median_time
from torch.utils.flop_counter import FlopCounterMode

from rangeret.models import build_model
from rangeret.models.blocks import token_mixing
from rangeret.models.blocks.decay import GridCache

MODELS = ("rangeret-thesis", "rangeret-cir")
RESOLUTIONS = ((64, 1024), (64, 2048))
CPU_PEAK_GFLOPS = 225.0


def parse_size(text: str) -> tuple[int, int]:
    """(height, width) from HEIGHTxWIDTH."""
    height, _, width = text.partition("x")
    return int(height), int(width)


def count_flops(model: torch.nn.Module, x: torch.Tensor) -> int:
    """FLOPs of one forward pass as torch's flop counter sees them (matmuls and convolutions)."""
    counter = FlopCounterMode(display=False)
    with torch.inference_mode(), counter:
        model(x)
    return counter.get_total_flops()


def time_forward(
    model: torch.nn.Module, x: torch.Tensor, repeat: int, autocast: torch.dtype | None = None
) -> float:
    """Median seconds of one forward pass, under autocast to `autocast` if given (synchronised on CUDA)."""
    cuda = x.device.type == "cuda"
    amp = (
        torch.autocast(x.device.type, dtype=autocast)
        if autocast is not None
        else contextlib.nullcontext()
    )

    def run() -> None:
        with torch.inference_mode(), amp:
            model(x)
        if cuda:
            torch.cuda.synchronize()

    return median_time(run, repeat=repeat, warmup=1)


def time_mixing(repeat: int) -> None:
    """One layer's token mixing at 64x1024 (3825 tokens, 4 heads): plain N x N form against tiles."""
    grid, heads = (15, 255), 4
    gen = torch.Generator().manual_seed(0)
    q, k, v = (torch.randn(1, heads, 3825, d, generator=gen) * 0.5 for d in (32, 32, 64))
    cache = GridCache("circular", heads, 32)
    cpu = torch.device("cpu")
    bias = cache.get("bias_full", grid, cpu, torch.float32)
    decay = torch.exp(bias)
    table_b = cache.get("bias_table", grid, cpu, torch.float32)
    table_d = cache.get("decay_table", grid, cpu, torch.float32)
    norm = cache.get("decay_norm", grid, cpu, torch.float32)
    cases = {
        "softmax + bias, plain": lambda: token_mixing.softmax_plain(q, k, v, bias),
        "softmax + bias, tiled": lambda: token_mixing.softmax_tiled(q, k, v, table_b, grid),
        "retention, plain": lambda: token_mixing.retention_plain(q, k, v, decay),
        "retention, tiled": lambda: token_mixing.retention_tiled(q, k, v, table_d, norm, grid),
    }
    print("token mixing of one layer at 64x1024, CPU fp32:")
    for label, fn in cases.items():
        with torch.inference_mode():
            seconds = median_time(fn, repeat=repeat)
        print(f"  {label:24} {seconds * 1000:8.1f} ms", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--repeat", type=int, default=3, help="timed passes per case (median reported)"
    )
    parser.add_argument(
        "--size",
        action="append",
        type=parse_size,
        help="HEIGHTxWIDTH to run, repeatable (default: 64x1024 and 64x2048)",
    )
    parser.add_argument(
        "--no-mixing", action="store_true", help="skip the per-layer token-mixing timings"
    )
    args = parser.parse_args()
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} CPU threads, CUDA: {torch.cuda.is_available()}"
    )
    print(
        f"{'model':16} {'size':>8} {'params':>10} {'GFLOP':>7} {'cpu s':>7} {'GFLOP/s':>8} {'of peak':>8}"
        f" {'bf16 s':>7}" + (f" {'cuda s':>7} {'fp16 s':>7}" if torch.cuda.is_available() else "")
    )
    for name in MODELS:
        for height, width in args.size or RESOLUTIONS:
            model = build_model(name, height=height, width=width).eval()
            x = torch.randn(1, 5, height, width)
            params = sum(p.numel() for p in model.parameters())
            gflop = count_flops(model, x) / 1e9
            seconds = time_forward(model, x, args.repeat)
            line = (
                f"{name:16} {height}x{width:<5} {params:>10,} {gflop:>7.1f} {seconds:>7.2f} "
                f"{gflop / seconds:>8.1f} {gflop / seconds / CPU_PEAK_GFLOPS:>8.0%}"
                f" {time_forward(model, x, args.repeat, autocast=torch.bfloat16):>7.2f}"
            )
            if torch.cuda.is_available():
                cuda = torch.device("cuda")
                model.to(cuda)
                xc = x.to(cuda)
                line += f" {time_forward(model, xc, 10):>7.4f} {time_forward(model, xc, 10, autocast=torch.float16):>7.4f}"
            print(line, flush=True)
    if not args.no_mixing:
        time_mixing(args.repeat)


if __name__ == "__main__":
    main()
