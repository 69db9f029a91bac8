"""A speed card for this machine: how fast a network labels a scan here, per precision and backend.

The card names the machine (CPU model and the flags that make bf16 and int8 products fast, torch's
threads; or the GPU), what `--precision auto` picks on it and why, and the network it timed. Then,
for each configuration (backend and precision: fp32 always, bf16 where the hardware runs it
natively, fp16 on CUDA, onnxruntime fp32 when asked for), the median and the spread over the
rounds of the forward pass, the projection, the kNN refinement (argmax and vote) and one scan end
to end, the scans per second that makes, the share of the scan's labels equal to torch fp32's, and
the fraction of this machine's measured square-matmul peak (at that precision) the forward pass
reaches, from the network's matmul and convolution FLOPs (`network_flops`).

Every configuration runs once untimed first (kernels built, labels kept for the agreement), then
the rounds go round robin over the configurations, starting one further along each round, so a
noisy spell hits every configuration alike. Nothing here is a fixed expectation: the numbers are
this machine's, at this moment.
"""

from __future__ import annotations

import platform
import statistics
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from rangeret.extras import extra_installed
from rangeret.inference.knn_native import describe as describe_knn
from rangeret.inference.predictor import Predictor
from rangeret.inference.runtime.cpu_features import FLAG_NAMES, FLAGS, cpu_features
from rangeret.inference.runtime.device import select_device
from rangeret.inference.runtime.precision import auto_choice, forward_precision
from rangeret.inference.spec import InferenceSpec
from rangeret.inference.speed_inputs import BenchError, BenchWeights

#: Timed rounds per configuration by default: a full-size network's card takes under a minute
#: on two cores.
DEFAULT_ROUNDS = 5
#: The torch dtype of each precision a matmul peak is measured at.
DTYPES = {"fp32": torch.float32, "bf16": torch.bfloat16, "fp16": torch.float16}


# The machine ------------------------------------------------------------------------------------


def machine(device: torch.device) -> dict[str, Any]:
    """The machine as the card names it: device, CPU (model, flags, threads), the GPU where the
    network runs on one, how kNN refinement votes there, and the versions of torch and
    onnxruntime."""
    gpu = None
    if device.type == "cuda":
        index = device.index if device.index is not None else torch.cuda.current_device()
        major, minor = torch.cuda.get_device_capability(index)
        gpu = {
            "name": torch.cuda.get_device_name(index),
            "capability": f"{major}.{minor}",
            "memory_gib": round(torch.cuda.get_device_properties(index).total_memory / 2**30, 1),
        }
    onnx = None
    if extra_installed("onnx"):
        import onnxruntime

        onnx = onnxruntime.__version__
    return {
        "device": str(device),
        "cpu": cpu_features().to_dict(),
        "gpu": gpu,
        "knn_vote": describe_knn(str(device)),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "onnxruntime": onnx,
    }


def machine_precisions(device: torch.device) -> list[str]:
    """The precisions worth timing here: fp32, bf16 where the hardware runs it natively (what
    `--precision auto` picks), fp16 on CUDA."""
    found = ["fp32"]
    if auto_choice(device).precision == "bf16":
        found.append("bf16")
    if device.type == "cuda":
        found.append("fp16")
    return found


def matmul_peak_gflops(device: torch.device, precision: str, budget_s: float = 0.5) -> float:
    """GFLOP/s of the fastest of a few square matmuls at `precision` on `device` (2048 on the
    CPU, 8192 on CUDA; fp32 without TF32): the peak the forward pass is measured against."""
    n = 8192 if device.type == "cuda" else 2048
    dtype = DTYPES[precision]
    a = torch.randn(n, n, device=device).to(dtype)
    b = torch.randn(n, n, device=device).to(dtype)
    best = float("inf")
    with torch.inference_mode(), forward_precision("fp32", device):
        torch.matmul(a, b)
        _sync(device)
        started = time.perf_counter()
        for _ in range(20):
            start = time.perf_counter()
            torch.matmul(a, b)
            _sync(device)
            best = min(best, time.perf_counter() - start)
            if time.perf_counter() - started > budget_s:
                break
    return 2 * n**3 / best / 1e9


def network_flops(network: torch.nn.Module) -> float | None:
    """FLOPs of one forward pass of a RangeRet network on one scan: its matrix products and
    convolutions, counted by torch's FLOP counter on a network of the same configuration built
    on the meta device (no weights, no arithmetic). The count is the network's own, whichever
    graph a run executes (a fused kernel hides its work from the counter). None for a network
    without a configuration."""
    from torch.utils.flop_counter import FlopCounterMode

    config = getattr(network, "config", None)
    if config is None:
        return None
    with torch.device("meta"):
        shape = type(network)(config).eval()
        scan = torch.zeros(1, config.in_channels, config.height, config.width)
    with torch.inference_mode(), FlopCounterMode(display=False) as counter:
        shape(scan)
    return float(counter.get_total_flops())


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


# The card ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Spread:
    """Seconds measured over the rounds: median, least and most."""

    median: float
    low: float
    high: float

    @classmethod
    def of(cls, seconds: Sequence[float]) -> Spread:
        return cls(statistics.median(seconds), min(seconds), max(seconds))

    def to_dict(self) -> dict[str, float]:
        """In milliseconds, for JSON."""
        return {
            "median_ms": round(1e3 * self.median, 3),
            "min_ms": round(1e3 * self.low, 3),
            "max_ms": round(1e3 * self.high, 3),
        }

    def text(self) -> str:
        """`median (least-most)` in milliseconds."""
        return f"{_ms(self.median)} ({_ms(self.low)}-{_ms(self.high)})"


def _ms(seconds: float) -> str:
    ms = 1e3 * seconds
    return f"{ms:.0f}" if ms >= 100 else f"{ms:.1f}"


@dataclass(frozen=True)
class ConfigResult:
    """One configuration's measurements (see the module)."""

    backend: str
    precision: str
    forward: Spread
    projection: Spread
    knn: Spread
    scan: Spread
    agreement: float
    gflops: float | None
    peak_fraction: float | None

    @property
    def scans_per_second(self) -> float:
        """Scans one after another, batch 1, at the median end-to-end time."""
        return 1.0 / self.scan.median

    def to_dict(self) -> dict[str, Any]:
        """Plain data for JSON."""
        return {
            "backend": self.backend,
            "precision": self.precision,
            "forward": self.forward.to_dict(),
            "projection": self.projection.to_dict(),
            "knn": self.knn.to_dict(),
            "scan": self.scan.to_dict(),
            "scans_per_second": round(self.scans_per_second, 3),
            "agreement_with_fp32": round(self.agreement, 6),
            "network_gflops_per_second": None if self.gflops is None else round(self.gflops, 1),
            "peak_fraction": None if self.peak_fraction is None else round(self.peak_fraction, 4),
        }


@dataclass(frozen=True)
class SpeedCard:
    """The measurements of one `measure` run, as JSON (`to_dict`) or a table (`text`)."""

    machine: dict[str, Any]
    auto: dict[str, str]
    network: dict[str, Any]
    scan: dict[str, Any]
    rounds: int
    peaks: dict[str, float]
    results: list[ConfigResult] = field(default_factory=list)
    seconds: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        """Plain data for JSON."""
        return {
            "machine": self.machine,
            "auto_precision": self.auto,
            "network": self.network,
            "scan": self.scan,
            "rounds": self.rounds,
            "matmul_peak_gflops": {k: round(v, 1) for k, v in self.peaks.items()},
            "results": [r.to_dict() for r in self.results],
            "seconds": round(self.seconds, 1),
        }

    def text(self) -> str:
        """The card as a table for people."""
        m, net = self.machine, self.network
        cpu = m["cpu"]
        flags = ", ".join(
            f"{FLAG_NAMES[flag]} {'yes' if cpu['flags'][flag] else 'no'}"
            for flag in FLAGS
            if flag != "amx_tile"
        )
        lines = [
            f"cpu       {cpu['model']}, {cpu['cpus']} CPUs, {cpu['torch_threads']} torch threads "
            f"(torch {m['torch']}, capability {cpu['torch_capability']})",
            f"flags     {flags}",
        ]
        if m["gpu"]:
            g = m["gpu"]
            lines.append(
                f"gpu       {g['name']} (compute capability {g['capability']}, "
                f"{g['memory_gib']} GiB)"
            )
        lines.append(f"knn       {m['knn_vote']}")
        lines.append(f"auto      {self.auto['precision']}: {self.auto['reason']}")
        weights = net["weights"] if net["note"] is None else f"{net['weights']} ({net['note']})"
        lines += [
            f"network   {net['model']}, {net['profile']} at {net['height']} x {net['width']}, "
            f"{net['gflop']:.1f} GFLOP per scan (matmuls and convolutions)",
            f"weights   {weights}",
            f"scan      {self.scan['source']}, {self.scan['points']:,} points; batch 1, "
            f"{self.rounds} round{'s' if self.rounds > 1 else ''}: median (least-most) ms",
            "peak      "
            + ", ".join(f"{p} {g:,.0f} GFLOP/s" for p, g in self.peaks.items())
            + " (square matmul)",
            "",
        ]
        header = (
            "backend",
            "precision",
            "forward ms",
            "projection ms",
            "kNN ms",
            "scan ms",
            "scans/s",
            "agree",
            "% of peak",
        )
        rows = [header]
        for r in self.results:
            rows.append(
                (
                    r.backend,
                    r.precision,
                    r.forward.text(),
                    r.projection.text(),
                    r.knn.text(),
                    r.scan.text(),
                    f"{r.scans_per_second:.2f}",
                    f"{100 * r.agreement:.2f}%",
                    "-" if r.peak_fraction is None else f"{100 * r.peak_fraction:.1f}%",
                )
            )
        widths = [max(len(row[i]) for row in rows) for i in range(len(header))]
        for row in rows:
            lines.append("  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)))
        return "\n".join(line.rstrip() for line in lines)


def configurations(
    device: torch.device, backends: Sequence[str], precisions: Sequence[str] | None = None
) -> list[tuple[str, str]]:
    """(backend, precision) pairs to time, torch fp32 first (the agreement's reference):
    `precisions` (default: `machine_precisions`) with torch, fp32 with onnxruntime."""
    found = [("torch", "fp32")]
    if "torch" in backends:
        found += [("torch", p) for p in precisions or machine_precisions(device) if p != "fp32"]
    if "onnxruntime" in backends:
        found.append(("onnxruntime", "fp32"))
    return found


def measure(
    bench: BenchWeights,
    points: np.ndarray,
    *,
    device: str = "auto",
    backends: Sequence[str] = ("torch",),
    precisions: Sequence[str] | None = None,
    rounds: int = DEFAULT_ROUNDS,
    scan_source: str = "simulated",
) -> SpeedCard:
    """The speed card of `bench`'s network labelling `points` on `device` (see the module)."""
    if rounds < 1:
        raise BenchError(f"--rounds must be at least 1, got {rounds}")
    started = time.perf_counter()
    dev = select_device(device)
    if "onnxruntime" in backends and not extra_installed("onnx"):
        raise BenchError("--backends onnxruntime needs the onnx extra: pip install rangeret[onnx]")
    configs = configurations(dev, backends, precisions)
    weights = bench.weights
    # onnxruntime's predictor moves the network to the CPU: built first, then torch's move it
    built = {
        c: Predictor(weights, InferenceSpec(device=str(dev), precision=c[1], backend=c[0]))
        for c in sorted(configs, key=lambda c: c[0] != "onnxruntime")
    }
    predictors = {c: built[c] for c in configs}
    reference = predictors[("torch", "fp32")]
    labels = {c: _scan(p, points)[1] for c, p in predictors.items()}
    flops = network_flops(weights.network) or 0.0
    peaks = {p: matmul_peak_gflops(dev, p) for p in sorted({c[1] for c in configs}, key=_order)}
    times: dict[tuple[str, str], list[tuple[float, float, float, float]]] = {c: [] for c in configs}
    for r in range(rounds):
        shift = r % len(configs)
        for config in configs[shift:] + configs[:shift]:
            times[config].append(_scan(predictors[config], points)[0])
    results = []
    for config in configs:
        projection, forward, knn, scan = (Spread.of(s) for s in zip(*times[config], strict=True))
        gflops = flops / forward.median / 1e9 if flops else None
        peak = peaks.get(config[1])
        results.append(
            ConfigResult(
                backend=config[0],
                precision=config[1],
                forward=forward,
                projection=projection,
                knn=knn,
                scan=scan,
                agreement=float(np.mean(labels[config] == labels[("torch", "fp32")])),
                gflops=gflops,
                peak_fraction=None if gflops is None or not peak else gflops / peak,
            )
        )
    auto = auto_choice(dev)
    p = reference.projection_config
    return SpeedCard(
        machine=machine(dev),
        auto={"precision": auto.precision, "reason": auto.reason},
        network={
            "model": bench.model,
            "weights": bench.source,
            "note": bench.note,
            "checkpoint_sha256": weights.sha256,
            "profile": weights.profile.name,
            "height": p.height,
            "width": p.width,
            "parameters": sum(t.numel() for t in weights.network.parameters()),
            "gflop": round(flops / 1e9, 3),
            "knn": reference.knn is not None,
        },
        scan={"source": scan_source, "points": len(points)},
        rounds=rounds,
        peaks=peaks,
        results=results,
        seconds=time.perf_counter() - started,
    )


def _order(precision: str) -> int:
    return list(DTYPES).index(precision)


def _scan(
    predictor: Predictor, points: np.ndarray
) -> tuple[tuple[float, float, float, float], np.ndarray]:
    """One scan end to end through the predictor's stages: (projection, forward, kNN, whole)
    seconds, and its raw labels."""
    t0 = time.perf_counter()
    projection = predictor.project(points)
    t1 = time.perf_counter()
    logits = predictor.logits([projection])
    t2 = time.perf_counter()
    (classes,) = predictor.refine_batch([projection], logits)
    t3 = time.perf_counter()
    raw = predictor.to_raw(classes)
    t4 = time.perf_counter()
    return (t1 - t0, t2 - t1, t3 - t2, t4 - t0), raw
