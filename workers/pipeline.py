"""The streaming prediction pipeline on Ray Data: read + project -> network + kNN -> write.

Scans are grouped into batches on the driver, in the same order and with the same composition as
`rangeret predict` uses, so both give bit-identical labels. Each batch flows through three stages:

- `stages.Reader` (`read_and_project`; small CPU actors, a fraction of a core each, one to
  max(2, model actors) of them): reads the scans and projects them; a scan that cannot be read
  travels on as a named failure.
- `ModelWorker` (an actor pool: one GPU each when the cluster has GPUs, CPU actors otherwise): the
  network on the batch, then kNN refinement and raw ids on the actor's device.
- `stages.Writer` (`write_results`; small CPU actors like the readers): atomic writes of the label
  files and, for labelled scans, per-scan confusion matrices, summed per batch.

The CPU stages are long-lived actors rather than tasks because Ray stops idle task workers once a
node holds more worker processes than CPUs, which model actors cause on small nodes; every batch
then paid a worker start-up (1-2 s of CPU). Measured on 2 cores, that churn cost more than the
network's own time per scan (`benchmarks/bench_workers.py`).

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

from rangeret.inference import PredictorSpec
from rangeret.io import read_labels
from rangeret.labels import LabelConfig
from rangeret.layout import ScanEntry, prediction_path
from rangeret.metrics import RawLabelEvaluator
from rangeret.profiles import DatasetProfile
from rangeret.timing import StageTimes
from workers.stages import ROW_COLUMN, BatchRecord, Reader, Writer

log = logging.getLogger(__name__)


GPU_ACTOR_CPUS = 0.5
"""CPUs a GPU model actor reserves (unpickling, host-device copies). Left unset, Ray would ask for
a whole CPU while the actor starts, which a GPU node whose CPUs readers hold cannot give: the
actor then never starts."""


class ClusterCapacityError(ValueError):
    """The cluster cannot start the model actors the run asked for."""


@dataclass(frozen=True)
class PipelineOptions:
    """How the pipeline runs: batch size, model actors and the CPU share of each stage.

    Model actors default to one per GPU. On CPU clusters they default to one per CPU that a reader
    and a writer leave free on the largest node, each with one torch thread: on 2 cores, two
    one-thread actors ran about 1.25x faster than one two-thread actor (`benchmarks/bench_workers.py`),
    as intra-op threads scale below linearly and stall whenever another process takes their core.
    Given `actors`, `actor_cpus` defaults to that free share split between them; the network runs
    on ceil(actor_cpus) threads. GPU actors reserve `actor_cpus` or `GPU_ACTOR_CPUS`.

    Batches flow once every model actor has started, so that each GPU works from the first batch
    on; `actor_start_timeout` seconds without them (long enough for an autoscaler to bring GPU
    nodes up) is a `ClusterCapacityError`.
    """

    batch_size: int = 1
    actors: int | None = None
    use_gpu: bool | None = None
    read_cpus: float = 0.25
    write_cpus: float = 0.1
    actor_start_timeout: float = 1800.0
    actor_cpus: float | None = None
    progress_interval: float = 10.0


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
    devices: list[str] = field(default_factory=list)


class ModelWorker:
    """Stage 2 (an actor): the network on a batch, then kNN refinement and raw ids."""

    def __init__(self, spec: PredictorSpec, cpus: float) -> None:
        import torch

        torch.set_num_threads(max(1, math.ceil(cpus)))
        self.predictor = spec.build()
        self.device = str(self.predictor.device)
        log.info("model worker %d on %s", os.getpid(), self.device)

    def __call__(self, batch: dict) -> dict:
        records = []
        for encoded in batch[ROW_COLUMN]:
            record = BatchRecord.decode({ROW_COLUMN: encoded})
            record.results = self.predictor.label_loaded(record.loaded, record.times)
            record.loaded = []
            record.worker = f"{self.device}@{os.getpid()}"
            records.append(record.encode()[ROW_COLUMN])
        return {ROW_COLUMN: records}


def cluster_gpus() -> int:
    """Number of GPUs the connected Ray cluster offers (0 on CPU-only clusters)."""
    import ray

    return int(ray.cluster_resources().get("GPU", 0))


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
    (`rangeret.inference.profile_for_checkpoint`): the readers take its point record and
    projection, the writers its labels.
    `progress(done, failed, total)` is called after every batch; setting `cancel` stops the run
    after the batch in flight (files already written stay complete).
    """
    import ray
    import ray.data

    out = str(out)
    gpus = cluster_gpus()
    use_gpu = gpus > 0 if options.use_gpu is None else options.use_gpu
    if use_gpu and not gpus:
        raise ValueError("GPU actors were asked for but the Ray cluster has no GPU")
    if use_gpu:
        actors, actor_cpus = options.actors or gpus, options.actor_cpus or GPU_ACTOR_CPUS
    else:
        actors, actor_cpus = _cpu_layout(options)
    result = PipelineResult(actors=actors, evaluator=RawLabelEvaluator(profile.labels))
    if not entries:
        return result

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

    actor_resources = (
        {"num_gpus": 1, "num_cpus": actor_cpus} if use_gpu else {"num_cpus": actor_cpus}
    )
    worker_spec = replace(spec, profile=profile)
    if not use_gpu and spec.device == "auto":
        worker_spec = replace(worker_spec, device="cpu")
    ds = ray.data.from_items(batches, override_num_blocks=len(batches))
    readers = ray.data.ActorPoolStrategy(min_size=1, max_size=max(2, actors))
    ds = ds.map(
        Reader,
        fn_constructor_kwargs={"projection": profile.projection, "record": profile.points},
        compute=readers,
        num_cpus=options.read_cpus,
    )
    ds = ds.map_batches(
        ModelWorker,
        fn_constructor_kwargs={"spec": worker_spec, "cpus": actor_cpus},
        compute=ray.data.ActorPoolStrategy(size=actors, max_tasks_in_flight_per_actor=2),
        batch_size=1,
        **actor_resources,
    )
    writers = ray.data.ActorPoolStrategy(min_size=1, max_size=max(2, actors))
    ds = ds.map(
        Writer,
        fn_constructor_kwargs={"out": out, "label_config": profile.labels},
        compute=writers,
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
        need = "1 GPU" if use_gpu else f"{actor_cpus:g} CPU"
        raise ClusterCapacityError(
            f"the {actors} model actor(s) did not start within {options.actor_start_timeout:g} s: "
            f"the Ray cluster does not offer {need} to each of them (see --actors)"
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


def _cpu_layout(options: PipelineOptions) -> tuple[int, float]:
    """CPU model actors and the CPUs of each: see `PipelineOptions`. The free CPUs are those of the
    largest node not held now (other actors, such as the gateway's, may hold some)."""
    import ray

    largest = max((n["Resources"].get("CPU", 0.0) for n in ray.nodes() if n["Alive"]), default=1.0)
    free = min(largest, ray.available_resources().get("CPU", 0.0))
    spare = free - options.read_cpus - options.write_cpus
    actors = options.actors or max(1, round(spare))
    cpus = options.actor_cpus or max(0.25, int(spare / actors * 4) / 4)
    return actors, cpus


def count_labels(
    entries: Iterable[ScanEntry], out: Path | str, label_config: LabelConfig
) -> RawLabelEvaluator:
    """Confusion counts of scans predicted earlier (skipped on resume), read from their files."""
    evaluator = RawLabelEvaluator(label_config)
    for entry in entries:
        if entry.label_path is None:
            continue
        pred = read_labels(prediction_path(out, entry.sequence, entry.name))
        evaluator.add(pred, read_labels(entry.label_path, num_points=pred.size))
    return evaluator
