"""Every GPU path checked in one run: environment, gpu tests, correctness, speed, kNN, pipeline.

`python3 benchmarks/gpu_check.py [--smoke] [--out DIR] [--max-seconds 270]`, from the repository
root with `PYTHONPATH=.`. It needs python with torch, numpy and pytest, nothing installed; the Ray
part of the pipeline section runs where Ray is importable. Results go to `DIR/gpu_check.json`,
`{"sections": {NAME: {"status", "seconds", ...figures}}}`, rewritten after every section (and
within the long ones), so a run stopped early leaves what it measured; a summary is printed at the
end. A section is "ok", "failed" (an error, with the end of its traceback, or a check that did not
hold) or "skipped" (with the reason); a failed section does not stop the others. Each section has
a time budget, and none starts once the whole run's `--max-seconds` would not leave it enough.

Without `--smoke` the sections run on the first CUDA device at the release's sizes (64 x 1024,
batches 1/8/32, 256 simulated scans); without a CUDA device the run stops after the environment
section. `--smoke` runs every section on the CPU at a tiny size, in well under a minute.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from _common import REAL_SCAN, REPO, SMALL_VECTORS

from rangeret.dataset.layout import KITTI_LAYOUT, ScanEntry, discover, prediction_path
from rangeret.dataset.profiles import DatasetProfile, load_profile
from rangeret.dataset.projection import project
from rangeret.inference.loading import LoadedScan, batches, load_batch, predict_loaded
from rangeret.inference.predictor import Predictor
from rangeret.inference.results import RunSummary
from rangeret.inference.runtime.precision import forward_precision
from rangeret.inference.spec import InferenceSpec
from rangeret.io.atomic import atomic_write_text
from rangeret.io.scans import read_scan, write_labels
from rangeret.knn import refine
from rangeret.models import build_model, load_checkpoint

NETWORKS = ("rangeret-thesis", "rangeret-cir")
PRECISIONS = ("fp32", "fp16", "bf16")
RESULT_FILE = "gpu_check.json"
#: Largest error of the published network's fp32 logits that counts as a match (as the tests).
PUBLISHED_LIMIT = 2e-4
#: The published test vectors' network: rangeret-cir at 32 x 256 with 2 blocks.
PUBLISHED_SIZE = (32, 256)
PUBLISHED_LAYERS = 2
SEED = 0

SIMULATE = """\
import sys
from rangeret.dataset.profiles import load_profile
from rangeret.sim import simulate_dataset
root, sequence, scans, height, width = sys.argv[1:]
profile = load_profile().with_overrides(height=int(height), width=int(width))
simulate_dataset(root, {sequence: int(scans)}, labelled=False, profile=profile)
"""


@dataclass(frozen=True)
class Plan:
    """Device and sizes of a run: the GPU's, or the smoke run's on the CPU."""

    smoke: bool
    device: str
    height: int
    width: int
    overrides: dict[str, int]
    precision_size: tuple[int, int]
    batches: tuple[int, ...]
    compare_batch: int
    warmup: int
    repeats: int
    measure_s: float
    pipeline_scans: int
    pipeline_batch: int
    pipeline_skip: int
    readers: int
    writers: int
    torch_threads: int | None

    @property
    def size(self) -> str:
        """The resolution as `H x W`."""
        return f"{self.height} x {self.width}"


def device_plan() -> Plan:
    """The GPU run: the release's resolution and depth, the deployment's batch sizes."""
    cpus = os.cpu_count() or 1
    return Plan(
        smoke=False,
        device="cuda",
        height=64,
        width=1024,
        overrides={},
        precision_size=PUBLISHED_SIZE,
        batches=(1, 8, 32),
        compare_batch=8,
        warmup=2,
        repeats=10,
        measure_s=1.5,
        pipeline_scans=256,
        pipeline_batch=8,
        pipeline_skip=4,
        readers=max(2, min(8, cpus - 2)),
        writers=4,
        torch_threads=None,
    )


def smoke_plan() -> Plan:
    """The smoke run: every section on the CPU at 8 x 64, one block, batches 1 and 2."""
    return Plan(
        smoke=True,
        device="cpu",
        height=8,
        width=64,
        overrides={"layers": 1},
        precision_size=(8, 64),
        batches=(1, 2),
        compare_batch=2,
        warmup=1,
        repeats=2,
        measure_s=0.5,
        pipeline_scans=6,
        pipeline_batch=2,
        pipeline_skip=1,
        readers=2,
        writers=1,
        torch_threads=1,
    )


class SectionSkipped(Exception):
    """Raised by a section that cannot run here; the message is the reason."""


@dataclass
class Context:
    """A run's plan, output file and clock, and the document written after every section."""

    plan: Plan
    out: Path
    max_seconds: float
    started: float = field(default_factory=time.monotonic)
    doc: dict[str, Any] = field(default_factory=lambda: {"sections": {}})
    section: str = ""
    section_started: float = 0.0
    section_deadline: float = 0.0
    figures: dict[str, Any] = field(default_factory=dict)

    @property
    def path(self) -> Path:
        """Where the JSON document is written."""
        return self.out / RESULT_FILE

    @property
    def device(self) -> torch.device:
        """The device under test."""
        return torch.device(self.plan.device)

    def run_left(self) -> float:
        """Seconds left of the whole run's budget."""
        return self.started + self.max_seconds - time.monotonic()

    def left(self) -> float:
        """Seconds left to the running section."""
        return self.section_deadline - time.monotonic()

    def save(self) -> None:
        """Write the document atomically."""
        self.doc["seconds"] = round(time.monotonic() - self.started, 3)
        atomic_write_text(self.path, json.dumps(self.doc, indent=2, default=str) + "\n")

    def progress(self) -> None:
        """Write the running section's figures so far."""
        seconds = round(time.monotonic() - self.section_started, 3)
        self.doc["sections"][self.section] = {
            "status": "running",
            "seconds": seconds,
            **self.figures,
        }
        self.save()


@dataclass(frozen=True)
class Section:
    """A section's body, the most seconds it may take and the fewest it needs to start."""

    run: Callable[[Context, dict[str, Any]], None]
    budget_s: float
    needs_s: float


def add_check(figures: dict[str, Any], name: str, ok: bool, detail: str) -> None:
    """Record a check; a check that does not hold fails its section."""
    figures.setdefault("checks", []).append({"name": name, "ok": bool(ok), "detail": detail})


def sync(device: torch.device) -> None:
    """Wait for the device's queued work (CUDA only)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def python_path() -> str:
    """PYTHONPATH that puts the repository first, for child processes."""
    rest = os.environ.get("PYTHONPATH")
    return os.pathsep.join([str(REPO), *([rest] if rest else [])])


def ray_version() -> tuple[str | None, str]:
    """Ray's version, or None and why it cannot be imported."""
    try:
        import ray
    except Exception as exc:
        return None, f"Ray is not importable ({type(exc).__name__}: {exc})"
    return str(ray.__version__), "importable"


def one_line(exc: BaseException) -> str:
    """An exception as one line: its type and the first line of its message."""
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


# --- environment ---------------------------------------------------------------------------


def nvml_info() -> dict[str, Any]:
    """Driver and GPUs as NVML reports them, where pynvml is importable."""
    try:
        import pynvml
    except Exception as exc:
        return {"available": False, "reason": f"pynvml is not importable ({one_line(exc)})"}
    try:
        pynvml.nvmlInit()
        try:
            gpus = []
            for i in range(pynvml.nvmlDeviceGetCount()):
                handle = pynvml.nvmlDeviceGetHandleByIndex(i)
                name = pynvml.nvmlDeviceGetName(handle)
                memory = pynvml.nvmlDeviceGetMemoryInfo(handle)
                gpus.append(
                    {
                        "index": i,
                        "name": name.decode() if isinstance(name, bytes) else str(name),
                        "memory_total_mib": memory.total // 2**20,
                        "memory_used_mib": memory.used // 2**20,
                    }
                )
            driver = pynvml.nvmlSystemGetDriverVersion()
            return {
                "available": True,
                "driver": driver.decode() if isinstance(driver, bytes) else str(driver),
                "gpus": gpus,
            }
        finally:
            pynvml.nvmlShutdown()
    except Exception as exc:
        return {"available": False, "reason": one_line(exc)}


def nvidia_smi_info() -> dict[str, Any]:
    """`nvidia-smi --query-gpu` output, where the command exists."""
    command = shutil.which("nvidia-smi")
    if command is None:
        return {"available": False, "reason": "nvidia-smi is not on PATH"}
    fields = "index,name,driver_version,memory.total,memory.used,utilization.gpu,temperature.gpu,power.draw,clocks.sm"
    try:
        run = subprocess.run(
            [command, f"--query-gpu={fields}", "--format=csv,noheader"],
            capture_output=True,
            text=True,
            timeout=20,
            check=False,
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        return {"available": False, "reason": one_line(exc)}
    if run.returncode != 0:
        return {"available": False, "reason": (run.stderr or run.stdout).strip()[-500:]}
    return {"available": True, "fields": fields, "gpus": run.stdout.strip().splitlines()}


def section_environment(ctx: Context, figures: dict[str, Any]) -> None:
    """Python, torch, CUDA, cuDNN, driver, GPUs, CPUs and whether Ray is importable."""
    ray, ray_reason = ray_version()
    cuda = torch.cuda.is_available()
    figures.update(
        mode="smoke" if ctx.plan.smoke else "device",
        device=ctx.plan.device,
        python=platform.python_version(),
        executable=sys.executable,
        platform=platform.platform(),
        numpy=np.__version__,
        torch=torch.__version__,
        torch_cuda_build=torch.version.cuda,
        cuda_available=cuda,
        cudnn=torch.backends.cudnn.version() if torch.backends.cudnn.is_available() else None,
        cpu_count=os.cpu_count(),
        usable_cpus=len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        torch_threads=torch.get_num_threads(),
        ray=ray,
        ray_importable=ray is not None,
        ray_reason=ray_reason,
    )
    gpus = []
    if cuda:
        for i in range(torch.cuda.device_count()):
            props = torch.cuda.get_device_properties(i)
            gpus.append(
                {
                    "index": i,
                    "name": props.name,
                    "memory_gib": round(props.total_memory / 2**30, 1),
                    "capability": f"{props.major}.{props.minor}",
                    "multiprocessors": props.multi_processor_count,
                }
            )
        figures["bf16_supported"] = torch.cuda.is_bf16_supported()
    figures["gpus"] = gpus
    figures["nvml"] = nvml_info()
    figures["nvidia_smi"] = nvidia_smi_info()
    gpu = f"{gpus[0]['name']} ({gpus[0]['memory_gib']} GiB)" if gpus else "no GPU"
    driver = figures["nvml"].get("driver") or (
        figures["nvidia_smi"]["gpus"][0].split(",")[2].strip()
        if figures["nvidia_smi"]["available"] and figures["nvidia_smi"]["gpus"]
        else "unknown"
    )
    figures["summary"] = (
        f"python {figures['python']}, torch {torch.__version__}, "
        f"CUDA {torch.version.cuda if cuda else 'not available'}, cuDNN {figures['cudnn']}, "
        f"{gpu}, driver {driver}, {os.cpu_count()} CPUs, "
        f"Ray {ray if ray else 'not importable'}"
    )


# --- tests ---------------------------------------------------------------------------------


def gpu_test_files() -> list[Path]:
    """The test files that hold tests with the `gpu` marker."""
    return [
        path
        for path in sorted((REPO / "tests").rglob("test_*.py"))
        if "mark.gpu" in path.read_text(encoding="utf-8")
    ]


def pytest_counts(output: str) -> tuple[dict[str, int], str]:
    """Outcome counts from pytest's last summary line, and that line."""
    pattern = re.compile(r"(\d+) (passed|failed|skipped|deselected|errors?|xfailed|xpassed)\b")
    for line in reversed(output.strip().splitlines()):
        found = pattern.findall(line)
        if found:
            counts: dict[str, int] = {}
            for number, outcome in found:
                key = "errors" if outcome.startswith("error") else outcome
                counts[key] = counts.get(key, 0) + int(number)
            return counts, line.strip("= ")
    return {}, ""


def section_tests(ctx: Context, figures: dict[str, Any]) -> None:
    """The `gpu`-marked tests, run by pytest in a child process."""
    files = [str(path.relative_to(REPO)) for path in gpu_test_files()]
    if not files:
        raise SectionSkipped("no test file carries the gpu marker")
    command = [sys.executable, "-m", "pytest", "-m", "gpu", "-q", "-p", "no:cacheprovider", *files]
    timeout = max(1.0, ctx.left())
    figures.update(command=" ".join(["python3", *command[1:]]), timeout_s=round(timeout, 1))
    env = {**os.environ, "PYTHONPATH": python_path()}
    try:
        run = subprocess.run(
            command,
            cwd=REPO,
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout,
            check=False,
        )
    except subprocess.TimeoutExpired as exc:
        out = exc.stdout or ""
        out = out.decode(errors="replace") if isinstance(out, bytes) else out
        figures["output_tail"] = out.strip().splitlines()[-20:]
        add_check(figures, "gpu tests", False, f"pytest did not finish within {timeout:.0f} s")
        return
    output = run.stdout + run.stderr
    counts, line = pytest_counts(run.stdout)
    for key in ("passed", "failed", "skipped", "errors"):
        counts.setdefault(key, 0)
    skips = [s for s in output.splitlines() if s.startswith("SKIPPED")]
    figures.update(
        returncode=run.returncode,
        counts=counts,
        result=line,
        skip_reasons=skips,
        output_tail=output.strip().splitlines()[-20:],
    )
    add_check(
        figures, "gpu tests", run.returncode == 0, f"pytest exit code {run.returncode}: {line}"
    )
    if ctx.device.type == "cuda":
        add_check(
            figures,
            "gpu tests ran",
            counts["skipped"] == 0 and counts["passed"] > 0,
            f"{counts['passed']} passed and {counts['skipped']} skipped on a CUDA machine",
        )
    elif counts["skipped"]:
        figures["note"] = "no CUDA device: the gpu tests skip, as they should"
    figures["summary"] = (
        f"{counts['passed']} passed, {counts['failed']} failed, {counts['skipped']} skipped, "
        f"{counts['errors']} errors ({', '.join(files)})"
        + (" - skipped without CUDA" if ctx.device.type != "cuda" and counts["skipped"] else "")
    )


# --- correctness ---------------------------------------------------------------------------


def load_vectors(path: Path) -> dict[str, Any]:
    """A test-vector file with its float16-stored state_dict and input upcast to float32."""
    vectors = torch.load(path, weights_only=False)
    vectors["state_dict"] = {
        k: v.float() if v.is_floating_point() else v for k, v in vectors["state_dict"].items()
    }
    vectors["input"] = vectors["input"].float()
    return vectors


def forward(
    network: torch.nn.Module, x: torch.Tensor, precision: str, device: torch.device
) -> torch.Tensor:
    """fp32 logits on the CPU of one forward pass at `precision` on `device`."""
    with torch.inference_mode(), forward_precision(precision, device):
        out = network(x.to(device))
    return out.float().cpu()


def agreement(a: torch.Tensor, b: torch.Tensor) -> float:
    """Share of pixels whose argmax over classes is the same in two (B, C, H, W) logits."""
    return float((a.argmax(1) == b.argmax(1)).float().mean())


def random_images(batch: int, height: int, width: int, seed: int) -> torch.Tensor:
    """Seeded random (B, 5, H, W) range images with 15 % of their pixels empty (zero)."""
    gen = torch.Generator().manual_seed(seed)
    images = torch.randn(batch, 5, height, width, generator=gen)
    empty = torch.rand(batch, 1, height, width, generator=gen) < 0.15
    return images.masked_fill(empty, 0.0)


def seeded_network(name: str, plan: Plan) -> torch.nn.Module:
    """Network `name` at the plan's resolution with seeded random weights."""
    torch.manual_seed(SEED)
    return build_model(name, plan.height, plan.width, **plan.overrides).eval()


def section_correctness(ctx: Context, figures: dict[str, Any]) -> None:
    """Published logits at fp32; fp16/bf16 and batched rows against fp32; CPU against device."""
    device, plan = ctx.device, ctx.plan
    vectors = load_vectors(SMALL_VECTORS)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "published.pt"
        torch.save(vectors["state_dict"], path)
        published = load_checkpoint(path, height=PUBLISHED_SIZE[0], width=PUBLISHED_SIZE[1])
    published = published.to(device).eval()
    expected = vectors["logits"].permute(0, 3, 1, 2).float()
    out = forward(published, vectors["input"], "fp32", device)
    error = float((out - expected).abs().max())
    figures["published_fp32"] = {
        "file": SMALL_VECTORS.name,
        "max_abs_error": error,
        "argmax_agreement": agreement(out, expected),
        "limit": PUBLISHED_LIMIT,
    }
    add_check(
        figures,
        "published logits at fp32",
        error <= PUBLISHED_LIMIT,
        f"max abs error {error:.2e} (limit {PUBLISHED_LIMIT:g})",
    )
    ctx.progress()

    h, w = plan.precision_size
    network = build_model("rangeret-cir", h, w, layers=PUBLISHED_LAYERS)
    network.load_state_dict(vectors["state_dict"])
    network = network.to(device).eval()
    x = vectors["input"][..., :h, :w]
    reference = forward(network, x, "fp32", device)
    precisions: dict[str, Any] = {"size": f"{h} x {w}", "weights": SMALL_VECTORS.name}
    for precision in ("fp16", "bf16"):
        low = forward(network, x, precision, device)
        finite = bool(torch.isfinite(low).all())
        precisions[precision] = {
            "max_abs_error": float((low - reference).abs().max()),
            "max_abs_fp32_logit": float(reference.abs().max()),
            "argmax_agreement": agreement(low, reference),
            "finite": finite,
        }
        add_check(figures, f"{precision} logits finite", finite, f"every {precision} logit finite")
    figures["precisions"] = precisions
    ctx.progress()

    images = torch.cat([x, random_images(plan.compare_batch - 1, h, w, SEED)])
    batched = forward(network, images, "fp32", device)
    single = torch.cat(
        [forward(network, images[i : i + 1], "fp32", device) for i in range(len(images))]
    )
    figures["batch_vs_single"] = {
        "batch": plan.compare_batch,
        "size": f"{h} x {w}",
        "precision": "fp32",
        "max_abs_difference": float((batched - single).abs().max()),
        "argmax_agreement": agreement(batched, single),
    }
    del network, published
    ctx.progress()

    points = read_scan(REAL_SCAN)
    profile = load_profile().with_overrides(height=plan.height, width=plan.width)
    labels: dict[str, Any] = {"scan": REAL_SCAN.name, "points": len(points), "size": plan.size}
    for name in NETWORKS:
        if ctx.left() <= 0:
            labels[name] = {"skipped": "time budget: the section's time is spent"}
            continue
        found: dict[str, np.ndarray] = {}
        seconds: dict[str, float] = {}
        for where in ("cpu", plan.device):
            predictor = Predictor.from_network(
                seeded_network(name, plan),
                profile,
                InferenceSpec(device=where, precision="fp32"),
            )
            if where != "cpu":  # the first call on a device pays for its start-up
                predictor.predict(points)
            start = time.perf_counter()
            found[where] = predictor.predict(points).labels
            seconds[where] = time.perf_counter() - start
        labels[name] = {
            "labels_equal": float(np.mean(found["cpu"] == found[plan.device])),
            "cpu_ms": round(1e3 * seconds["cpu"], 2),
            "device_ms": round(1e3 * seconds[plan.device], 2),
        }
        ctx.progress()
    labels["compared"] = f"cpu against {plan.device}"
    figures["cpu_vs_device_labels"] = labels
    figures["summary"] = (
        f"published fp32 max error {error:.1e}; "
        + "; ".join(
            f"{p} max error {precisions[p]['max_abs_error']:.1e}, argmax {precisions[p]['argmax_agreement']:.4f}"
            for p in ("fp16", "bf16")
        )
        + f"; batch {plan.compare_batch} vs 1 max {figures['batch_vs_single']['max_abs_difference']:.1e}"
        + "; labels cpu = "
        + plan.device
        + ": "
        + ", ".join(
            f"{n} {labels[n]['labels_equal']:.4f}"
            if "labels_equal" in labels[n]
            else f"{n} skipped"
            for n in NETWORKS
        )
    )


# --- throughput ----------------------------------------------------------------------------


def time_forward(
    network: torch.nn.Module, x: torch.Tensor, precision: str, plan: Plan, device: torch.device
) -> tuple[list[float], bool]:
    """Seconds of timed forward passes after warm-up, and whether the last logits were finite."""
    with torch.inference_mode(), forward_precision(precision, device):
        out = None
        for _ in range(plan.warmup):
            out = network(x)
        sync(device)
        times: list[float] = []
        until = time.perf_counter() + plan.measure_s
        while len(times) < plan.repeats and (len(times) < 2 or time.perf_counter() < until):
            start = time.perf_counter()
            out = network(x)
            sync(device)
            times.append(time.perf_counter() - start)
        finite = bool(torch.isfinite(out).all())
    return times, finite


def section_throughput(ctx: Context, figures: dict[str, Any]) -> None:
    """Median ms per batch, scans/s and peak memory of both networks at every precision and batch."""
    device, plan = ctx.device, ctx.plan
    runs: list[dict[str, Any]] = []
    figures.update(size=plan.size, device=plan.device, runs=runs)
    gen = torch.Generator().manual_seed(SEED)
    last = 0.0
    for name in NETWORKS:
        network = seeded_network(name, plan).to(device)
        for precision in PRECISIONS:
            for batch in plan.batches:
                run: dict[str, Any] = {"network": name, "precision": precision, "batch": batch}
                runs.append(run)
                if ctx.left() < last:
                    run["skipped"] = (
                        f"time budget: {max(0.0, ctx.left()):.0f} s left to the section, "
                        f"the last combination took {last:.0f} s"
                    )
                    continue
                start = time.perf_counter()
                try:
                    x = torch.randn(batch, 5, plan.height, plan.width, generator=gen).to(device)
                    if device.type == "cuda":
                        torch.cuda.empty_cache()
                        torch.cuda.reset_peak_memory_stats(device)
                    times, finite = time_forward(network, x, precision, plan, device)
                except RuntimeError as exc:  # out of device memory, say: the others still run
                    run["error"] = one_line(exc)
                    continue
                finally:
                    last = time.perf_counter() - start
                median = statistics.median(times)
                run.update(
                    median_ms=round(1e3 * median, 3),
                    scans_per_s=round(batch / median, 2),
                    repeats=len(times),
                    finite=finite,
                    peak_memory_mib=(
                        round(torch.cuda.max_memory_allocated(device) / 2**20, 1)
                        if device.type == "cuda"
                        else None
                    ),
                )
                ctx.progress()
        del network
        if device.type == "cuda":
            torch.cuda.empty_cache()
    errors = [r for r in runs if "error" in r]
    add_check(
        figures,
        "every combination ran",
        not errors,
        "; ".join(
            f"{r['network']} {r['precision']} batch {r['batch']}: {r['error']}" for r in errors
        )
        or "no errors",
    )
    infinite = [r for r in runs if r.get("finite") is False]
    add_check(
        figures,
        "logits finite",
        not infinite,
        ", ".join(f"{r['network']} {r['precision']} batch {r['batch']}" for r in infinite)
        or "every combination gave finite logits",
    )
    best = []
    for name in NETWORKS:
        done = [r for r in runs if r["network"] == name and "scans_per_s" in r]
        if done:
            top = max(done, key=lambda r: r["scans_per_s"])
            best.append(
                f"{name} {top['scans_per_s']:.1f} scans/s ({top['precision']}, batch {top['batch']})"
            )
    skipped = sum("skipped" in r for r in runs)
    figures["summary"] = (
        f"at {plan.size}: "
        + "; ".join(best)
        + (f"; {skipped} combinations skipped for time" if skipped else "")
    )


# --- knn -----------------------------------------------------------------------------------


def timed(
    fn: Callable[[], torch.Tensor], device: torch.device, repeats: int
) -> tuple[torch.Tensor, float]:
    """The result of `fn()` and its median ms over `repeats` runs after one warm-up."""
    result = fn()
    sync(device)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        sync(device)
        times.append(time.perf_counter() - start)
    return result, 1e3 * statistics.median(times)


def section_knn(ctx: Context, figures: dict[str, Any]) -> None:
    """kNN refinement of the real scan on the device against the CPU: equal labels, ms each."""
    device = ctx.device
    points = read_scan(REAL_SCAN)
    projection = project(points)
    height, width = projection.proj_range.shape
    argmax = torch.randint(0, 20, (height, width), generator=torch.Generator().manual_seed(SEED))
    inputs = [
        torch.from_numpy(projection.proj_range),
        torch.from_numpy(projection.unproj_range),
        argmax,
        torch.from_numpy(projection.proj_x),
        torch.from_numpy(projection.proj_y),
    ]
    repeats = max(3, ctx.plan.repeats)
    cpu, cpu_ms = timed(lambda: refine(*inputs), torch.device("cpu"), repeats)
    on_device = [t.to(device) for t in inputs]
    found, device_ms = timed(lambda: refine(*on_device), device, repeats)
    equal = float((found.cpu() == cpu).float().mean())
    figures.update(
        scan=REAL_SCAN.name,
        points=len(points),
        size=f"{height} x {width}",
        argmax="seeded random classes",
        labels_equal=equal,
        cpu_ms=round(cpu_ms, 3),
        device_ms=round(device_ms, 3),
        device=str(device),
    )
    add_check(
        figures, "kNN labels equal to the CPU's", equal == 1.0, f"{equal:.6f} of points equal"
    )
    figures["summary"] = (
        f"{len(points):,} points: labels equal {equal:.6f}, cpu {cpu_ms:.1f} ms, {device} {device_ms:.1f} ms"
    )


# --- pipeline ------------------------------------------------------------------------------


class UtilisationSampler:
    """GPU utilisation sampled in a thread: NVML where pynvml imports, else nvidia-smi."""

    def __init__(self, device: torch.device, interval: float = 0.1) -> None:
        self.samples: list[tuple[float, float]] = []
        self.interval = interval
        self.index = self._physical_index(device)
        self.source, self._read = self._reader(device)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    @staticmethod
    def _physical_index(device: torch.device) -> int:
        """The GPU's index as NVML counts them (CUDA_VISIBLE_DEVICES may renumber them)."""
        if device.type != "cuda":
            return 0
        visible = [
            v.strip() for v in os.environ.get("CUDA_VISIBLE_DEVICES", "").split(",") if v.strip()
        ]
        current = torch.cuda.current_device() if device.index is None else device.index
        if visible and current < len(visible) and visible[current].isdigit():
            return int(visible[current])
        return current

    def _reader(self, device: torch.device) -> tuple[str, Callable[[], float] | None]:
        """The source's name and a function that reads one sample."""
        if device.type != "cuda":
            return "unavailable: no CUDA device", None
        try:
            import pynvml

            pynvml.nvmlInit()
            handle = pynvml.nvmlDeviceGetHandleByIndex(self.index)
            pynvml.nvmlDeviceGetUtilizationRates(handle)
            return "pynvml", lambda: float(pynvml.nvmlDeviceGetUtilizationRates(handle).gpu)
        except Exception:
            pass
        command = shutil.which("nvidia-smi")
        if command is None:
            return "unavailable: neither pynvml nor nvidia-smi", None
        query = [
            command,
            "--query-gpu=utilization.gpu",
            "--format=csv,noheader,nounits",
            "-i",
            str(self.index),
        ]

        def read() -> float:
            run = subprocess.run(query, capture_output=True, text=True, timeout=5, check=True)
            return float(run.stdout.strip().splitlines()[0])

        try:
            read()
        except (OSError, ValueError, IndexError, subprocess.SubprocessError) as exc:
            return f"unavailable: nvidia-smi failed ({one_line(exc)})", None
        return "nvidia-smi", read

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                value = self._read()
            except Exception:
                value = None
            if value is not None:
                self.samples.append((time.perf_counter(), value))
            self._stop.wait(self.interval)

    @contextmanager
    def running(self) -> Iterator[UtilisationSampler]:
        """Sample while the body runs."""
        if self._read is not None:
            self._thread.start()
        try:
            yield self
        finally:
            self._stop.set()
            if self._thread.is_alive():
                self._thread.join(timeout=10)

    def between(self, start: float, stop: float) -> dict[str, Any]:
        """Mean and median utilisation (%) of the samples taken between two perf_counter times."""
        values = [v for t, v in self.samples if start <= t <= stop]
        if not values:
            return {"source": self.source, "samples": 0}
        return {
            "source": self.source,
            "samples": len(values),
            "mean_percent": round(statistics.fmean(values), 1),
            "median_percent": round(statistics.median(values), 1),
        }


def simulated_scans(ctx: Context, figures: dict[str, Any]) -> tuple[Path, list[str]]:
    """The pipeline's simulated scans, cached under the output folder (made in parallel)."""
    plan = ctx.plan
    workers = max(1, min(os.cpu_count() or 1, 8, plan.pipeline_scans))
    counts = [
        plan.pipeline_scans // workers + (i < plan.pipeline_scans % workers) for i in range(workers)
    ]
    sequences = [f"{i:02d}" for i in range(workers)]
    root = ctx.out / "gpu_check_scans" / f"{plan.height}x{plan.width}-{plan.pipeline_scans}-seed0"
    marker = root / "complete.json"
    if marker.exists():
        figures["scans_cached"] = str(root)
        return root, sorted(json.loads(marker.read_text())["sequences"])
    partial = root.with_name(root.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    shutil.rmtree(root, ignore_errors=True)
    start = time.perf_counter()
    env = {**os.environ, "PYTHONPATH": python_path()}
    children = [
        subprocess.Popen(
            [
                sys.executable,
                "-c",
                SIMULATE,
                str(partial),
                seq,
                str(n),
                str(plan.height),
                str(plan.width),
            ],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for seq, n in zip(sequences, counts, strict=True)
    ]
    failures = []
    for child in children:
        _, err = child.communicate()
        if child.returncode:
            failures.append(
                err.strip().splitlines()[-1] if err.strip() else f"exit {child.returncode}"
            )
    if failures:
        raise RuntimeError(f"simulating the scans failed: {failures[0]}")
    atomic_write_text(
        partial / "complete.json",
        json.dumps(
            {"scans": plan.pipeline_scans, "sequences": dict(zip(sequences, counts, strict=True))}
        ),
    )
    partial.rename(root)
    figures["simulated_s"] = round(time.perf_counter() - start, 2)
    return root, sequences


def label_in_process(
    predictor: Predictor,
    entries: Sequence[ScanEntry],
    out: Path,
    plan: Plan,
    sampler: UtilisationSampler,
) -> dict[str, Any]:
    """One GPU actor's work in this process: reader threads, the network and kNN, writer threads."""
    summary = RunSummary(total=len(entries))
    times = summary.times
    size = plan.pipeline_batch
    scan_batches = batches(entries, size)
    config, record = predictor.projection_config, predictor.profile.points
    done_at: list[float] = []
    writes: list[tuple[str, int, Future[None]]] = []

    def write(entry: ScanEntry, labels: np.ndarray) -> None:
        with times.stage("write"):
            write_labels(prediction_path(out, entry.sequence, entry.name), labels)

    start = time.perf_counter()
    with (
        ThreadPoolExecutor(plan.readers, thread_name_prefix="reader") as readers,
        ThreadPoolExecutor(plan.writers, thread_name_prefix="writer") as writers,
    ):
        upcoming = iter(scan_batches)
        pending: deque[Future[list[LoadedScan]]] = deque()

        def refill() -> None:
            while len(pending) < 2 * plan.readers:
                batch = next(upcoming, None)
                if batch is None:
                    return
                pending.append(readers.submit(load_batch, batch, config, times, record=record))

        refill()
        while pending:
            loaded = pending.popleft().result()
            refill()
            results = predict_loaded(predictor, loaded, times)
            done_at.append(time.perf_counter())
            for scan, found in zip(loaded, results, strict=True):
                if isinstance(found, str):
                    summary.add(scan.entry.key, found)
                else:
                    written = writers.submit(write, scan.entry, found.labels)
                    writes.append((scan.entry.key, scan.projection.num_points, written))
        labelled = time.perf_counter()
        for key, points, future in writes:
            future.result()
            summary.add(key, None, points)
    summary.seconds = total = time.perf_counter() - start
    skip = plan.pipeline_skip
    steady: dict[str, Any] = {"skipped_batches": skip}
    if len(scan_batches) > skip >= 1:
        window = done_at[-1] - done_at[skip - 1]
        scans = sum(len(b) for b in scan_batches[skip:])
        steady.update(scans=scans, seconds=round(window, 3), scans_per_s=round(scans / window, 2))
        steady["gpu_utilisation"] = sampler.between(done_at[skip - 1], done_at[-1])
    return {
        "scans": summary.total,
        "written": summary.written,
        "failed": summary.failed,
        "batch": size,
        "readers": plan.readers,
        "writers": plan.writers,
        "seconds": round(total, 3),
        "scans_per_s_overall": round(len(entries) / total, 2),
        "write_backlog_s": round(total - (labelled - start), 3),
        "steady_state": steady,
        "stage_ms_per_scan": {k: round(v, 3) for k, v in times.per_scan_ms().items()},
    }


def label_on_ray(
    spec: InferenceSpec,
    profile: DatasetProfile,
    entries: Sequence[ScanEntry],
    out: Path,
    plan: Plan,
) -> dict[str, Any]:
    """The same scans through the Ray pipeline (`workers.pipeline.run_pipeline`) on a local Ray."""
    import ray

    from workers.pipeline import run_pipeline
    from workers.sizing import PipelineOptions

    os.environ["PYTHONPATH"] = python_path()  # Ray's worker processes import `workers` from here
    gpus = torch.cuda.device_count() if torch.cuda.is_available() else 0
    start = time.perf_counter()
    ray.init(num_cpus=os.cpu_count(), num_gpus=gpus, include_dashboard=False, log_to_driver=False)
    try:
        started = time.perf_counter() - start
        run = run_pipeline(
            spec,
            profile,
            entries,
            out,
            PipelineOptions(batch_size=plan.pipeline_batch, actor_start_timeout=90),
        )
    finally:
        ray.shutdown()
    summary = run.summary
    return {
        "ray_start_s": round(started, 2),
        "seconds": round(summary.seconds, 3),
        "written": summary.written,
        "failed": summary.failed,
        "actors": run.layout.actors if run.layout is not None else 0,
        "workers": run.devices,
        "scans_per_s": round(summary.written / summary.seconds, 2) if summary.seconds else None,
        "stage_ms_per_scan": {k: round(v, 3) for k, v in summary.times.per_scan_ms().items()},
    }


def same_labels(entries: Sequence[ScanEntry], first: Path, second: Path) -> float:
    """Share of scans whose label files are byte-identical in two prediction trees."""
    same = 0
    for entry in entries:
        a = prediction_path(first, entry.sequence, entry.name)
        b = prediction_path(second, entry.sequence, entry.name)
        same += a.exists() and b.exists() and a.read_bytes() == b.read_bytes()
    return same / max(len(entries), 1)


def section_pipeline(ctx: Context, figures: dict[str, Any]) -> None:
    """Simulated scans through one process's readers, network, kNN and writers; then on Ray."""
    device, plan = ctx.device, ctx.plan
    root, sequences = simulated_scans(ctx, figures)
    entries = discover(root, sequences, layout=KITTI_LAYOUT).scans
    figures.update(scans=len(entries), size=plan.size, network="rangeret-cir", data=str(root))
    ctx.progress()
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
        checkpoint = tmp_path / "rangeret-cir.pt"
        torch.save(seeded_network("rangeret-cir", plan).state_dict(), checkpoint)
        spec = InferenceSpec(
            checkpoint=str(checkpoint),
            height=plan.height,
            width=plan.width,
            device=plan.device,
            precision="auto",
        )
        predictor = Predictor.from_spec(spec)
        figures["precision"] = predictor.precision
        if device.type == "cuda":
            torch.cuda.empty_cache()
            torch.cuda.reset_peak_memory_stats(device)
        with UtilisationSampler(device).running() as sampler:
            in_process = label_in_process(
                predictor, entries, tmp_path / "in-process", plan, sampler
            )
        if device.type == "cuda":
            in_process["peak_memory_mib"] = round(
                torch.cuda.max_memory_allocated(device) / 2**20, 1
            )
        figures["in_process"] = in_process
        add_check(
            figures,
            "every scan labelled in process",
            in_process["written"] == len(entries),
            f"{in_process['written']} of {len(entries)} written; failures: {in_process['failed'] or 'none'}",
        )
        ctx.progress()

        version, reason = ray_version()
        if plan.smoke:
            figures["ray"] = {
                "status": "skipped",
                "reason": "--smoke: a local Ray takes longer to start than a smoke run allows",
            }
        elif version is None:
            figures["ray"] = {"status": "skipped", "reason": reason}
        elif ctx.left() < 45:
            figures["ray"] = {
                "status": "skipped",
                "reason": f"time budget: {max(0.0, ctx.left()):.0f} s left, the Ray run needs about 45 s",
            }
        else:
            profile = predictor.profile
            del predictor
            if device.type == "cuda":
                torch.cuda.empty_cache()
            ray_run = label_on_ray(spec, profile, entries, tmp_path / "ray", plan)
            ray_run["labels_identical_to_in_process"] = same_labels(
                entries, tmp_path / "in-process", tmp_path / "ray"
            )
            figures["ray"] = {"status": "ok", "version": version, **ray_run}
            add_check(
                figures,
                "Ray labels identical to the in-process run",
                ray_run["labels_identical_to_in_process"] == 1.0,
                f"{ray_run['labels_identical_to_in_process']:.4f} of scans byte-identical",
            )
    steady = figures["in_process"]["steady_state"]
    utilisation = steady.get("gpu_utilisation", {})
    ray_part = figures["ray"]
    figures["summary"] = (
        f"{len(entries)} scans, batch {plan.pipeline_batch}, {figures['precision']}: "
        f"{steady.get('scans_per_s', 'n/a')} scans/s steady "
        f"({figures['in_process']['scans_per_s_overall']} overall), GPU utilisation "
        f"{utilisation.get('mean_percent', utilisation.get('source', 'n/a'))}"
        + (
            f"; Ray {ray_part['scans_per_s']} scans/s"
            if ray_part["status"] == "ok"
            else f"; Ray skipped ({ray_part['reason']})"
        )
    )


# --- the run -------------------------------------------------------------------------------

SECTIONS: dict[str, Section] = {
    "environment": Section(section_environment, budget_s=30, needs_s=0),
    "tests": Section(section_tests, budget_s=75, needs_s=20),
    "correctness": Section(section_correctness, budget_s=60, needs_s=10),
    "throughput": Section(section_throughput, budget_s=80, needs_s=15),
    "knn": Section(section_knn, budget_s=20, needs_s=3),
    "pipeline": Section(section_pipeline, budget_s=100, needs_s=20),
}


def run_sections(ctx: Context, sections: dict[str, Section]) -> dict[str, Any]:
    """Run each section in turn, recording its status, seconds and figures after each."""
    ctx.out.mkdir(parents=True, exist_ok=True)
    ctx.doc.update(mode="smoke" if ctx.plan.smoke else "device", complete=False)
    for name, section in sections.items():
        left = ctx.run_left()
        if section.needs_s > 0 and left < section.needs_s:
            ctx.doc["sections"][name] = {
                "status": "skipped",
                "seconds": 0.0,
                "reason": f"time budget: {max(0.0, left):.0f} s left of --max-seconds "
                f"{ctx.max_seconds:g}, the section needs at least {section.needs_s:g} s",
            }
            ctx.save()
            print(f"  {name}: skipped for time", flush=True)
            continue
        ctx.section, ctx.figures = name, {}
        ctx.section_started = time.monotonic()
        ctx.section_deadline = ctx.section_started + min(section.budget_s, max(left, 0.0))
        ctx.progress()
        entry: dict[str, Any]
        try:
            section.run(ctx, ctx.figures)
        except SectionSkipped as exc:
            entry = {"status": "skipped", "reason": str(exc)}
        except Exception as exc:
            tail = traceback.format_exc().strip().splitlines()[-12:]
            entry = {"status": "failed", "error": one_line(exc), "traceback": tail}
        else:
            broken = [c for c in ctx.figures.get("checks", []) if not c["ok"]]
            entry = (
                {
                    "status": "failed",
                    "error": "; ".join(f"{c['name']}: {c['detail']}" for c in broken),
                }
                if broken
                else {"status": "ok"}
            )
        seconds = round(time.monotonic() - ctx.section_started, 3)
        ctx.doc["sections"][name] = {
            "status": entry.pop("status"),
            "seconds": seconds,
            **entry,
            **ctx.figures,
        }
        ctx.save()
        print(f"  {name}: {ctx.doc['sections'][name]['status']} in {seconds:.1f} s", flush=True)
    ctx.doc["complete"] = True
    ctx.save()
    return ctx.doc


def summary(doc: dict[str, Any], path: Path) -> str:
    """The readable summary printed at the end of a run."""
    sections = doc["sections"]
    states = [s["status"] for s in sections.values()]
    lines = [
        f"gpu check ({doc.get('mode')}): {states.count('ok')} ok, {states.count('failed')} failed, "
        f"{states.count('skipped')} skipped in {doc.get('seconds', 0):.1f} s -> {path}"
    ]
    for name, s in sections.items():
        detail = (
            s.get("summary", "") if s["status"] == "ok" else s.get("error") or s.get("reason", "")
        )
        lines.append(f"  {name:12s} {s['status']:8s} {s['seconds']:6.1f} s  {detail}")
        if name == "throughput":
            for run in s.get("runs", []):
                label = f"    {run['network']:16s} {run['precision']:5s} batch {run['batch']:3d}"
                if "median_ms" in run:
                    memory = run["peak_memory_mib"]
                    lines.append(
                        f"{label}  {run['median_ms']:9.2f} ms  {run['scans_per_s']:9.1f} scans/s"
                        + (f"  peak {memory:9.1f} MiB" if memory is not None else "")
                    )
                else:
                    lines.append(f"{label}  {run.get('error') or run.get('skipped')}")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Parse the options, run the sections and print the summary; 0 when none failed."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--smoke", action="store_true", help="every section on the CPU, tiny sizes")
    parser.add_argument("--out", type=Path, default=Path("."), help="folder of gpu_check.json")
    parser.add_argument(
        "--max-seconds",
        type=float,
        default=270.0,
        help="the whole run's time budget: sections that would exceed it are skipped",
    )
    args = parser.parse_args(argv)
    plan = smoke_plan() if args.smoke else device_plan()
    if plan.torch_threads:
        torch.set_num_threads(plan.torch_threads)
    ctx = Context(plan=plan, out=args.out, max_seconds=args.max_seconds)
    print(f"gpu check ({'smoke, cpu' if plan.smoke else 'cuda'}) -> {ctx.path}", flush=True)
    if not plan.smoke and not torch.cuda.is_available():
        run_sections(ctx, {"environment": SECTIONS["environment"]})
        print(summary(ctx.doc, ctx.path))
        print(
            f"no CUDA device: torch {torch.__version__} (CUDA build {torch.version.cuda}) sees "
            "none, so only the environment section ran; --smoke runs every section on the CPU",
            file=sys.stderr,
        )
        return 2
    doc = run_sections(ctx, SECTIONS)
    print(summary(doc, ctx.path))
    return 1 if any(s["status"] == "failed" for s in doc["sections"].values()) else 0


if __name__ == "__main__":
    sys.exit(main())
