"""The streaming prediction pipeline on Ray Data: read + project -> network + kNN -> write.

Scans are grouped into batches on the driver, in the same order and with the same composition as
`rangeret predict` uses, so both give bit-identical labels. Each batch flows through three stages:

- `stages.Reader` (`read_and_project`; small CPU actors, a fraction of a core each): reads the
  scans and projects them; a scan that cannot be read travels on as a named failure.
- `stages.ModelWorker` (an actor pool: one GPU each when the cluster has GPUs, CPU actors
  otherwise): the network on the batch, then kNN refinement and raw ids on the actor's device,
  and with the spec's `panoptic` the objects, clustered by the actor's `Predictor` as
  `rangeret predict --panoptic` clusters them.
- `stages.Writer` (`write_results`; small CPU actors like the readers): atomic writes of the label
  files (with `panoptic`, the layout's panoptic files at the places the entries of a panoptic
  selection name) and, for labelled scans, per-scan confusion matrices of the semantic labels,
  summed per batch.

How many actors each stage gets is `workers.sizing.plan_layout`'s (see `PipelineOptions`), for
the resources `workers.cluster` reads. The CPU stages are long-lived actors rather than tasks
because Ray stops idle task workers once a node holds more worker processes than CPUs, which model
actors cause on small nodes; every batch then paid a worker start-up, which on small nodes cost
more than the network's own time per scan (`benchmarks/bench_workers.py` measures the stages).

The driver tallies each scan in a `RunSummary`, sums the matrices (reduction by addition) and logs
progress. Ray Data restarts dead actors, on other nodes when theirs is gone, and retries their
batches, so a crash costs no scan; every write is atomic, so a retried batch leaves the same files.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from rangeret.dataset.layout import ScanEntry
from rangeret.dataset.profiles import DatasetProfile
from rangeret.evaluation.counting import RawLabelEvaluator
from rangeret.exceptions import InputError
from rangeret.inference.description import describe_network
from rangeret.inference.loading import batches
from rangeret.inference.results import RunSummary
from rangeret.inference.spec import InferenceSpec
from workers.cluster import cluster_layout
from workers.progress import TimeLeft
from workers.sizing import ClusterCapacityError, Layout, PipelineOptions
from workers.stages import BatchRecord, ModelWorker, Reader, Writer

if TYPE_CHECKING:  # torch stays out of the driver until a model actor needs it
    from rangeret.models.weights.checkpoint_info import CheckpointInfo

log = logging.getLogger(__name__)

#: The options of a run that names none.
DEFAULT_OPTIONS = PipelineOptions()


@dataclass
class PipelineRun:
    """What `run_pipeline` did: the `RunSummary` of its scans, their summed confusion counts, the
    layout it ran with (None when there was nothing to do) and the devices of its model actors."""

    summary: RunSummary
    evaluator: RawLabelEvaluator
    layout: Layout | None = None
    devices: list[str] = field(default_factory=list)

    def actors_text(self) -> str:
        """The model actors by device, for people: `cpu (2 model actors: processes 14452,
        14460)`; "no model actor" when none ran."""
        by_device: dict[str, list[str]] = {}
        for worker in self.devices:
            device, _, pid = worker.partition("@")
            by_device.setdefault(device, []).append(pid)
        if not by_device:
            return "no model actor"
        parts = []
        for device, pids in sorted(by_device.items()):
            count = f"{len(pids)} model actor{'s' if len(pids) > 1 else ''}"
            parts.append(
                f"{device} ({count}: process{'es' if len(pids) > 1 else ''} {', '.join(pids)})"
            )
        return ", ".join(parts)

    def precision(self, spec: InferenceSpec) -> str | None:
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


def describe_spec(spec: InferenceSpec, info: CheckpointInfo, profile: DatasetProfile) -> dict:
    """The network description `run.json` records for a pipeline run of `spec` (the device and
    precision asked for: the model actors resolve them)."""
    return describe_network(
        model=info.name,
        checkpoint=info.path,
        sha256=info.sha256,
        profile=profile.name,
        projection=profile.projection,
        knn=spec.knn_settings,
        tta=spec.tta,
        device=spec.device,
        precision=spec.precision,
        backend=spec.backend,
        parent=info.parent,
        clustering=spec.clustering,
    )


def run_pipeline(
    spec: InferenceSpec,
    profile: DatasetProfile,
    entries: Sequence[ScanEntry],
    out: Path | str,
    options: PipelineOptions = DEFAULT_OPTIONS,
    progress: Callable[[int, int, int], None] | None = None,
    cancel: threading.Event | None = None,
    checkpoint_sha256: str | None = None,
) -> PipelineRun:
    """Predict `entries` into the tree at `out` on the connected Ray cluster.

    `profile` must be the one `spec`'s weights run with (`rangeret.inference.loaded_weights.load_weights`
    settled it): the readers take its point record and projection, the model actors load the
    weights for it, the writers take its labels. With `spec.panoptic`, `entries` are those of a
    panoptic selection (`DatasetSelection.for_task(True)`) and a profile without thing classes is
    an `InputError` before any actor starts. The run's summary counts `entries` only.
    `progress(done, failed, total)` is called after every batch; setting `cancel` stops the run
    after the batch in flight (files already written stay complete). With `checkpoint_sha256`
    (what the driver read), a model actor that finds other bytes at the checkpoint's path fails
    instead of labelling with them.
    """
    import ray
    import ray.data

    refusal = profile.panoptic_refusal() if spec.panoptic else None
    if refusal is not None:
        raise InputError(refusal)
    out = str(out)
    summary = RunSummary(total=len(entries))
    run = PipelineRun(summary, RawLabelEvaluator.for_profile(profile))
    if not entries:
        return run
    layout = run.layout = cluster_layout(options)
    log.info("pipeline: %s", layout.describe(options))

    records = [
        BatchRecord(i, batch).encode()
        for i, batch in enumerate(batches(entries, options.batch_size))
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

    ds = ray.data.from_items(records, override_num_blocks=len(records))
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
    worker_spec = spec
    if layout.model == "cpu" and spec.device == "auto":
        worker_spec = spec.replace(device="cpu")
    ds = ds.map_batches(
        ModelWorker,
        fn_constructor_kwargs={
            "spec": worker_spec,
            "profile": profile,
            "cpus": layout.actor_cpus,
            "checkpoint_sha256": checkpoint_sha256,
        },
        compute=ray.data.ActorPoolStrategy(
            size=layout.actors, max_tasks_in_flight_per_actor=layout.in_flight
        ),
        batch_size=1,
        num_cpus=layout.actor_cpus,
        **({"num_gpus": 1} if layout.model == "gpu" else {}),
    )
    ds = ds.map(
        Writer,
        fn_constructor_kwargs={"out": out, "profile": profile, "panoptic": spec.panoptic},
        compute=ray.data.ActorPoolStrategy(min_size=1, max_size=layout.writers),
        num_cpus=options.write_cpus,
    )

    start = time.perf_counter()
    last_log = start
    total = len(entries)
    time_left = TimeLeft(total)
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
            log.info("cancelled after %d of %d scans", summary.done, total)
            break
        record = BatchRecord.decode(row)
        for entry, error in zip(record.entries, record.failures, strict=True):
            summary.add(entry.key, error)
        summary.points += record.points
        summary.times.merge(record.times)
        run.evaluator.merge(record.counts)
        devices.add(record.worker)
        if progress is not None:
            progress(summary.done, len(summary.failed), total)
        now = time.perf_counter()
        left = time_left.update(summary.done)
        if now - last_log >= options.progress_interval or summary.done == total:
            log.info(
                "%d / %d scans done (%d failed), %.2f scans/s%s",
                summary.done,
                total,
                len(summary.failed),
                summary.done / (now - start),
                f", about {left:.0f} s left" if left else "",
            )
            last_log = now
    summary.seconds = time.perf_counter() - start
    run.devices = sorted(devices)
    return run
