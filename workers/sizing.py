"""How many actors each stage of a prediction run gets: a pure function of what the cluster offers.

`plan_layout(options, resources)` turns a `ClusterResources` snapshot (the cluster's totals, what is
free now, each live node's CPUs, and what an autoscaler may add) into a `Layout`: model actors,
the CPUs of each, readers and writers. `replica_gpus` sizes the Serve replicas the same way.
Nothing here talks to Ray (`workers.cluster` reads the snapshot), so every layout is tested
with plain dicts.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, field

from rangeret.exceptions import ResourceError

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
"""Free CPU cores per writer beside GPU model actors: writing a scan is far cheaper than reading
and projecting it (`benchmarks/bench_workers.py`), so one writer keeps up with several readers."""


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
    each): a 16-core node with one GPU gets up to 13 readers and 2 writers. Each reader reserves
    `read_cpus` and each writer `write_cpus`; Ray Data starts more of them while batches wait.

    CPU clusters: model actors default to one per CPU that a reader and a writer leave free on the
    largest node, each with one torch thread: two one-thread actors outrun one two-thread actor
    (`benchmarks/bench_workers.py` compares them), as intra-op threads scale
    below linearly and stall whenever another process takes their core. Given `actors`,
    `actor_cpus` defaults to that free share split between them; the network runs on
    ceil(actor_cpus) threads. Readers and writers: up to max(2, model actors) of each.

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
class ClusterResources:
    """What a cluster offers at one moment, as Ray reports it: `total` (`ray.cluster_resources()`),
    `available` (`ray.available_resources()`), the CPUs of each live node (`ray.nodes()`), and
    `autoscaler`, the most of each resource an autoscaler may grow the cluster to (empty for a
    fixed cluster)."""

    total: Mapping[str, float] = field(default_factory=dict)
    available: Mapping[str, float] = field(default_factory=dict)
    node_cpus: tuple[float, ...] = ()
    autoscaler: Mapping[str, float] = field(default_factory=dict)

    @property
    def gpus(self) -> int:
        """GPUs the cluster has now (0 on CPU-only clusters)."""
        return int(self.total.get("GPU", 0))

    @property
    def free_gpus(self) -> int:
        """GPUs no actor holds now."""
        return int(self.available.get("GPU", 0))

    @property
    def free_cpus(self) -> float:
        """CPUs no actor holds now, over the whole cluster."""
        return float(self.available.get("CPU", 0.0))

    @property
    def most_gpus(self) -> int:
        """The most GPUs the autoscaler may grow the cluster to; 0 without an autoscaler."""
        return int(self.autoscaler.get("GPU", 0))


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


def uses_gpu(options: PipelineOptions, resources: ClusterResources) -> bool:
    """Whether the model actors take GPUs: as `options.use_gpu` says, else where the cluster has
    any; `ValueError` when GPUs are asked for on a cluster without one."""
    use_gpu = resources.gpus > 0 if options.use_gpu is None else options.use_gpu
    if use_gpu and not resources.gpus:
        raise ClusterCapacityError("GPU actors were asked for but the Ray cluster has no GPU")
    return use_gpu


def waits_for_gpu(options: PipelineOptions, resources: ClusterResources) -> bool:
    """Whether a run should wait (up to `FREE_GPU_WAIT_S`) before its layout is chosen: it sizes
    its GPU model actors from the free GPUs and none is free now."""
    return uses_gpu(options, resources) and options.actors is None and resources.free_gpus == 0


def plan_layout(options: PipelineOptions, resources: ClusterResources) -> Layout:
    """The actors of each stage for a run on a cluster offering `resources` (see
    `PipelineOptions`)."""
    if not uses_gpu(options, resources):
        actors, actor_cpus = cpu_layout(options, resources)
        return Layout("cpu", actors, actor_cpus, max(2, actors), max(2, actors))
    actors = options.actors or free_gpu_actors(resources)
    actor_cpus = options.actor_cpus or GPU_ACTOR_CPUS
    readers, writers = gpu_feeders(resources.free_cpus, actors * actor_cpus)
    return Layout("gpu", actors, actor_cpus, readers, writers)


def free_gpu_actors(resources: ClusterResources) -> int:
    """GPU model actors for a run that names no count: one per free GPU; one when none is free but
    an autoscaler can add GPUs (it then waits `actor_start_timeout` for them); otherwise a
    `ClusterCapacityError` naming the numbers."""
    if resources.free_gpus:
        return resources.free_gpus
    gpus, most = resources.gpus, resources.most_gpus
    if most > gpus:
        log.info("no GPU is free; the autoscaler can grow the cluster to %d GPUs: waiting", most)
        return 1
    raise ClusterCapacityError(
        f"none of the Ray cluster's {gpus} GPU(s) is free (0 of {gpus} after "
        f"{FREE_GPU_WAIT_S:g} s: other actors, such as the Serve application's replicas, hold "
        "them) and the cluster cannot grow: give the cluster more GPUs, an autoscaler, or lower "
        "the Serve application's max_replicas"
    )


def gpu_feeders(free_cpus: float, model_cpus: float) -> tuple[int, int]:
    """The most readers and writers beside GPU model actors that reserve `model_cpus` of the
    cluster's `free_cpus`: see `PipelineOptions`."""
    spare = max(0.0, free_cpus - model_cpus)
    writers = max(2, math.ceil(spare / CORES_PER_GPU_WRITER))
    return max(2, math.floor(spare) - writers), writers


def cpu_layout(options: PipelineOptions, resources: ClusterResources) -> tuple[int, float]:
    """CPU model actors and the CPUs of each: see `PipelineOptions`. The free CPUs are those of the
    largest node not held now (other actors, such as Serve replicas, may hold some)."""
    largest = max(resources.node_cpus, default=1.0)
    free = min(largest, resources.free_cpus)
    spare = free - options.read_cpus - options.write_cpus
    actors = options.actors or max(1, round(spare))
    cpus = options.actor_cpus or max(0.25, int(spare / actors * 4) / 4)
    return actors, cpus


def replica_gpus(device: str, resources: ClusterResources) -> float:
    """GPUs each Serve replica asks for: one on `cuda`, none on `cpu`, and for `auto` one where
    the cluster has GPUs or its autoscaler can add them."""
    if device != "auto":
        return 1.0 if device == "cuda" else 0.0
    return 1.0 if resources.gpus or resources.most_gpus else 0.0
