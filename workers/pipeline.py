"""The streaming prediction pipeline on Ray Data: read + project -> network + kNN -> write.

Scans are grouped into batches on the driver, in the same order and with the same composition as
`rangeret predict` uses, so both give bit-identical labels. Each batch flows through three stages:

- `stages.Reader` (`read_and_project`; small CPU actors, a fraction of a core each): reads the
  scans and projects them; a scan that cannot be read travels on as a named failure.
- `ModelWorker` (an actor pool: one GPU each when the cluster has GPUs, CPU actors otherwise): the
  network on the batch, then kNN refinement and raw ids on the actor's device.
- `stages.Writer` (`write_results`; small CPU actors like the readers): atomic writes of the label
  files and, for labelled scans, per-scan confusion matrices, summed per batch.

How many actors each stage gets is `plan_layout`'s (see `PipelineOptions`). The CPU stages are
long-lived actors rather than tasks because Ray stops idle task workers once a node holds more
worker processes than CPUs, which model actors cause on small nodes; every batch then paid a
worker start-up (1-2 s of CPU). Measured on 2 cores, that churn cost more than the network's own
time per scan (`benchmarks/bench_workers.py`).

The driver sums the matrices (reduction by addition) and logs progress. Ray Data restarts dead
actors, on other nodes when theirs is gone, and retries their batches, so a crash costs no scan;
every write is atomic, so a retried batch leaves the same files.
"""

from __future__ import annotations

import itertools
import logging
import math
import os
import threading
import time
import warnings
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from rangeret.dataset.layout import ScanEntry, prediction_path
from rangeret.dataset.profiles import DatasetProfile
from rangeret.evaluation.evaluate import count_scan
from rangeret.evaluation.metrics import RawLabelEvaluator
from rangeret.exceptions import ResourceError
from rangeret.inference.timing import StageTimes
from workers.stages import ROW_COLUMN, BatchRecord, Reader, Writer

if TYPE_CHECKING:  # torch stays out of the driver until a model actor needs it
    from rangeret.inference.predictor import Predictor, PredictorSpec

log = logging.getLogger(__name__)


GPU_ACTOR_CPUS = 0.5
"""CPUs a GPU model actor reserves (unpickling, host-device copies). Left unset, Ray would ask for
a whole CPU while the actor starts, which a GPU node whose CPUs readers hold cannot give: the
actor then never starts."""

GPU_TASKS_IN_FLIGHT = 4
"""Batches sent to each GPU model actor at once: one on the GPU and three whose rows Ray pulls to
the actor's node meanwhile, so a slow transfer or a reader's pause does not leave the GPU idle.
More would only hold more projected scans (about 5 MB each) in the object store."""

CPU_TASKS_IN_FLIGHT = 2
"""Batches sent to each CPU model actor at once: one running, one arriving. A batch takes a CPU
actor seconds, so a deeper queue only leaves the last batches behind one actor while others idle."""

FREE_GPU_WAIT_S = 10.0
"""How long a run that finds no free GPU waits for one before it fails: actors that are ending
(those of a job that has just finished) give their GPUs back within seconds."""

CORES_PER_GPU_WRITER = 8
"""Free CPU cores per writer beside GPU model actors: writing a scan takes about 1 ms, reading
and projecting it about 20 ms, so one writer keeps up with several readers."""


class ClusterCapacityError(ResourceError, ValueError):
    """The cluster cannot start the model actors the run asked for."""


@dataclass(frozen=True)
class PipelineOptions:
    """How the pipeline runs: batch size, model actors and the CPU share of each stage.

    GPU clusters: model actors default to one per GPU free when the run starts
    (`ray.available_resources()`: Serve replicas may hold some GPUs), each reserving
    `actor_cpus` or `GPU_ACTOR_CPUS`. With no GPU free after `FREE_GPU_WAIT_S` seconds the run is a
    `ClusterCapacityError` naming the numbers, unless an autoscaler can add GPUs (one actor then
    waits for them). Readers: up to one per CPU core of the cluster that the model actors leave
    free, less the writers, which get one per `CORES_PER_GPU_WRITER` such cores (at least 2 of
    each). Reading and projecting a 120k-point scan takes about 20 ms of one core, so a 16-core node
    with one GPU gets up to 13 readers (about 650 scans/s) and 2 writers. Each reader reserves
    `read_cpus` and each writer `write_cpus`; Ray Data starts more of them while batches wait.

    CPU clusters: model actors default to one per CPU that a reader and a writer leave free on the
    largest node, each with one torch thread: on 2 cores, two one-thread actors ran about 1.25x
    faster than one two-thread actor (`benchmarks/bench_workers.py`), as intra-op threads scale
    below linearly and stall whenever another process takes their core. Given `actors`,
    `actor_cpus` defaults to that free share split between them; the network runs on
    ceil(actor_cpus) threads. Readers and writers: up to max(2, model actors) of each, the layout
    measured on 2 cores.

    `actors`, `use_gpu` and `actor_cpus` shape the model actors a run starts. Batches flow once every
    model actor has started, so that each GPU works from the first batch on;
    `actor_start_timeout` seconds without them (long enough for an autoscaler to bring GPU nodes
    up) is a `ClusterCapacityError`.
    """

    batch_size: int = 1
    actors: int | None = None
    use_gpu: bool | None = None
    read_cpus: float = 0.25
    write_cpus: float = 0.1
    actor_start_timeout: float = 1800.0
    actor_cpus: float | None = None
    progress_interval: float = 10.0
    #: Folders the readers may read scans from (links resolved); None: anywhere.
    read_roots: tuple[str, ...] | None = None


@dataclass(frozen=True)
class Layout:
    """The actors of each stage of a run: `model` is "gpu" or "cpu"; readers and writers are the
    most of each."""

    model: str
    actors: int
    actor_cpus: float
    readers: int
    writers: int

    @property
    def in_flight(self) -> int:
        """Batches sent to each model actor at once (see the *_TASKS_IN_FLIGHT constants)."""
        return GPU_TASKS_IN_FLIGHT if self.model == "gpu" else CPU_TASKS_IN_FLIGHT

    def describe(self, options: PipelineOptions) -> str:
        """One line for the job's log."""
        gpu = "1 GPU + " if self.model == "gpu" else ""
        model = f"{self.actors} model actor(s) ({gpu}{self.actor_cpus:g} CPU each)"
        return (
            f"{model}, {self.in_flight} batch(es) of {options.batch_size} scan(s) in flight "
            f"each; up to {self.readers} readers ({options.read_cpus:g} CPU each) and "
            f"{self.writers} writers ({options.write_cpus:g} CPU each)"
        )


@dataclass
class PipelineResult:
    """What the pipeline did: scans written, failures by scan, the summed confusion counts."""

    written: int = 0
    points: int = 0
    failed: dict[str, str] = field(default_factory=dict)
    evaluator: RawLabelEvaluator = field(default_factory=RawLabelEvaluator)
    times: StageTimes = field(default_factory=StageTimes)
    seconds: float = 0.0
    actors: int = 0
    readers: int = 0
    writers: int = 0
    devices: list[str] = field(default_factory=list)

    def precision(self, spec: PredictorSpec) -> str | None:
        """The precision the network ran at on the run's devices (`auto` resolved per device
        type, as each model actor resolved it), comma-separated; None when no batch ran."""
        import torch

        from rangeret.inference.runtime.precision import resolve_precision

        kinds = {d.split("@")[0].split(":")[0] for d in self.devices}
        if not kinds:
            return None
        return ", ".join(
            sorted(
                {resolve_precision(spec.precision, torch.device(k), spec.backend) for k in kinds}
            )
        )


def warm_up(predictor: Predictor) -> float:
    """Run the network once on an empty scan's range image (zeros of (1, 5, H, W)), so that the
    decay tables and the device's kernels are built before the first real batch; the time it took
    is logged and returned, and recorded in no stage."""
    start = time.perf_counter()
    empty = predictor.project(np.zeros((0, 5), np.float32), StageTimes())
    predictor.logits([empty], StageTimes())
    seconds = time.perf_counter() - start
    config = predictor.projection_config
    log.info(
        "model actor %d warmed up on %s (%d x %d) in %.2f s",
        os.getpid(),
        predictor.device,
        config.height,
        config.width,
        seconds,
    )
    return seconds


def label_batch(predictor: Predictor, encoded: bytes) -> bytes:
    """Stage 2 on one encoded `BatchRecord`: the network, kNN refinement and raw ids of its
    scans; the record names the device and process that ran it."""
    record = BatchRecord.decode({ROW_COLUMN: encoded})
    record.results = [
        (None if found is None else found.labels, error)
        for found, error in predictor.label_loaded(record.loaded, record.times)
    ]
    record.loaded = []
    record.worker = f"{predictor.device}@{os.getpid()}"
    return record.encode()[ROW_COLUMN]


class ModelWorker:
    """Stage 2 (an actor): the network on a batch, then kNN refinement and raw ids. It warms the
    network up before it takes a batch, so the first batch's times are those of any other."""

    def __init__(self, spec: PredictorSpec, cpus: float) -> None:
        import torch

        torch.set_num_threads(max(1, math.ceil(cpus)))
        self.predictor = spec.build()
        self.warm_up_seconds = warm_up(self.predictor)

    def __call__(self, batch: dict) -> dict:
        return {ROW_COLUMN: [label_batch(self.predictor, row) for row in batch[ROW_COLUMN]]}


def cluster_gpus() -> int:
    """Number of GPUs the connected Ray cluster offers (0 on CPU-only clusters)."""
    import ray

    return int(ray.cluster_resources().get("GPU", 0))


def gpu_feeders(free_cpus: float, model_cpus: float) -> tuple[int, int]:
    """The most readers and writers beside GPU model actors that reserve `model_cpus` of the
    cluster's `free_cpus`: see `PipelineOptions`."""
    spare = max(0.0, free_cpus - model_cpus)
    writers = max(2, math.ceil(spare / CORES_PER_GPU_WRITER))
    return max(2, math.floor(spare) - writers), writers


def plan_layout(options: PipelineOptions) -> Layout:
    """The actors of each stage for a run on the connected cluster (see `PipelineOptions`)."""
    import ray

    gpus = cluster_gpus()
    use_gpu = gpus > 0 if options.use_gpu is None else options.use_gpu
    if use_gpu and not gpus:
        raise ClusterCapacityError("GPU actors were asked for but the Ray cluster has no GPU")
    if not use_gpu:
        actors, actor_cpus = _cpu_layout(options)
        return Layout("cpu", actors, actor_cpus, max(2, actors), max(2, actors))
    actors = options.actors or _free_gpus(gpus)
    actor_cpus = options.actor_cpus or GPU_ACTOR_CPUS
    readers, writers = gpu_feeders(ray.available_resources().get("CPU", 0.0), actors * actor_cpus)
    return Layout("gpu", actors, actor_cpus, readers, writers)


def run_pipeline(
    spec: PredictorSpec,
    profile: DatasetProfile,
    entries: Sequence[ScanEntry],
    out: Path | str,
    options: PipelineOptions = PipelineOptions(),
    progress: Callable[[int, int, int], None] | None = None,
    cancel: threading.Event | None = None,
) -> PipelineResult:
    """Predict `entries` into the tree at `out` on the connected Ray cluster.

    `profile` must be the one `spec`'s predictor runs with
    (`rangeret.models.weights.run_profile.profile_for_checkpoint`): the readers take its point record and
    projection, the writers its labels.
    `progress(done, failed, total)` is called after every batch; setting `cancel` stops the run
    after the batch in flight (files already written stay complete).
    """
    import ray
    import ray.data

    out = str(out)
    result = PipelineResult(evaluator=RawLabelEvaluator(config=profile.labels))
    if not entries:
        return result
    layout = plan_layout(options)
    result.actors, result.readers, result.writers = layout.actors, layout.readers, layout.writers
    log.info("pipeline: %s", layout.describe(options))

    batches = [
        BatchRecord(i, list(entries[s : s + options.batch_size])).encode()
        for i, s in enumerate(range(0, len(entries), options.batch_size))
    ]
    ctx = ray.data.DataContext.get_current()
    ctx.enable_progress_bars = False
    ctx.execution_options.preserve_order = False
    ctx.wait_for_min_actors_s = int(options.actor_start_timeout)
    # Spread batches over every model actor instead of favouring the one beside the reader that
    # made them: a projected scan is a few MB, cheap to move, and idle GPUs are not. Ray 2.60 marks
    # the switch deprecated but honours it; the two-GPU cluster test fails without it.
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*actor_locality_enabled")
        ctx.execution_options.actor_locality_enabled = False

    ds = ray.data.from_items(batches, override_num_blocks=len(batches))
    ds = ds.map(
        Reader,
        fn_constructor_kwargs={
            "projection": profile.projection,
            "record": profile.points,
            "within": options.read_roots,
        },
        compute=ray.data.ActorPoolStrategy(min_size=1, max_size=layout.readers),
        num_cpus=options.read_cpus,
    )
    worker_spec = replace(spec, profile=profile)
    if layout.model == "cpu" and spec.device == "auto":
        worker_spec = replace(worker_spec, device="cpu")
    ds = ds.map_batches(
        ModelWorker,
        fn_constructor_kwargs={"spec": worker_spec, "cpus": layout.actor_cpus},
        compute=ray.data.ActorPoolStrategy(
            size=layout.actors, max_tasks_in_flight_per_actor=layout.in_flight
        ),
        batch_size=1,
        num_cpus=layout.actor_cpus,
        **({"num_gpus": 1} if layout.model == "gpu" else {}),
    )
    ds = ds.map(
        Writer,
        fn_constructor_kwargs={"out": out, "label_config": profile.labels},
        compute=ray.data.ActorPoolStrategy(min_size=1, max_size=layout.writers),
        num_cpus=options.write_cpus,
    )

    start = time.perf_counter()
    last_log = start
    total = len(entries)
    seen = 0
    devices: set[str] = set()
    try:
        rows = iter(ds.iter_rows())
        first = next(rows, None)
    except ray.exceptions.GetTimeoutError as exc:
        need = {"gpu": "1 GPU", "cpu": f"{layout.actor_cpus:g} CPU"}
        raise ClusterCapacityError(
            f"the pipeline's actors ({layout.describe(options)}) did not start within "
            f"{options.actor_start_timeout:g} s: the Ray cluster does not offer "
            f"{need[layout.model]} to each model actor (see --actors)"
        ) from exc
    for row in itertools.chain([first] if first is not None else [], rows):
        if cancel is not None and cancel.is_set():
            log.info("cancelled after %d of %d scans", seen, total)
            break
        record = BatchRecord.decode(row)
        for entry, error in zip(record.entries, record.failures, strict=True):
            seen += 1
            if error is None:
                result.written += 1
            else:
                result.failed[entry.key] = error
        result.points += record.points
        result.evaluator.merge(record.counts)
        result.times.merge(record.times)
        devices.add(record.worker)
        if progress is not None:
            progress(seen, len(result.failed), total)
        now = time.perf_counter()
        if now - last_log >= options.progress_interval or seen == total:
            rate = seen / (now - start)
            left = (total - seen) / rate if rate else float("inf")
            log.info(
                "%d / %d scans done (%d failed), %.2f scans/s, about %.0f s left",
                seen,
                total,
                len(result.failed),
                rate,
                left,
            )
            last_log = now
    result.seconds = time.perf_counter() - start
    result.devices = sorted(devices)
    return result


def _free_gpus(gpus: int) -> int:
    """GPU model actors for a run that names no count: one per GPU free now, waiting up to
    `FREE_GPU_WAIT_S` for one; one when none is free but an autoscaler can add GPUs (it then waits
    `actor_start_timeout` for them); otherwise a `ClusterCapacityError` naming the numbers."""
    import ray

    deadline = time.monotonic() + FREE_GPU_WAIT_S
    while not (free := int(ray.available_resources().get("GPU", 0))):
        if time.monotonic() >= deadline:
            break
        time.sleep(0.5)
    if free:
        return free
    most = autoscaler_gpus()
    if most > gpus:
        log.info("no GPU is free; the autoscaler can grow the cluster to %d GPUs: waiting", most)
        return 1
    raise ClusterCapacityError(
        f"none of the Ray cluster's {gpus} GPU(s) is free (0 of {gpus} after "
        f"{FREE_GPU_WAIT_S:g} s: other actors, such as the Serve application's replicas, hold "
        "them) and the cluster cannot grow: give the cluster more GPUs, an autoscaler, or lower "
        "the Serve application's max_replicas"
    )


def autoscaler_gpus() -> int:
    """The most GPUs the autoscaler may grow the cluster to, as Ray Train reads it; 0 where no
    autoscaler reports one (a fixed cluster) or the driver cannot ask (through Ray Client)."""
    import ray
    from ray._private.state import state

    try:
        most = state.get_max_resources_from_cluster_config() or {}
    except ray.exceptions.RaySystemError:
        return 0
    return int(most.get("GPU", 0))


def _cpu_layout(options: PipelineOptions) -> tuple[int, float]:
    """CPU model actors and the CPUs of each: see `PipelineOptions`. The free CPUs are those of the
    largest node not held now (other actors, such as Serve replicas, may hold some)."""
    import ray

    largest = max((n["Resources"].get("CPU", 0.0) for n in ray.nodes() if n["Alive"]), default=1.0)
    free = min(largest, ray.available_resources().get("CPU", 0.0))
    spare = free - options.read_cpus - options.write_cpus
    actors = options.actors or max(1, round(spare))
    cpus = options.actor_cpus or max(0.25, int(spare / actors * 4) / 4)
    return actors, cpus


def count_labels(
    entries: Iterable[ScanEntry], out: Path | str, profile: DatasetProfile
) -> RawLabelEvaluator:
    """Confusion counts of scans predicted earlier (skipped on resume), read from their files as
    `rangeret evaluate` reads them (the scan for its points' distance bands)."""
    evaluator = RawLabelEvaluator(config=profile.labels)
    for entry in entries:
        if entry.label_path is not None:
            pred = prediction_path(out, entry.sequence, entry.name)
            count_scan(evaluator, entry, pred, profile.points)
    return evaluator
