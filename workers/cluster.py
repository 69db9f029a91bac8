"""What the connected Ray cluster offers, read into a `workers.sizing.ClusterResources` snapshot.

Totals, free resources and the live nodes come from Ray's public API (`ray.cluster_resources()`,
`ray.available_resources()`, `ray.nodes()`). The most an autoscaler may grow the cluster to has no
public call: `autoscaler_limits` reads it from the autoscaler's cluster config, as Ray Train and
Ray Data do, and reads nothing (a fixed cluster) where that is not possible.
"""

from __future__ import annotations

import logging
import os
import time

from workers.sizing import (
    FREE_GPU_WAIT_S,
    ClusterResources,
    Layout,
    PipelineOptions,
    plan_layout,
    waits_for_gpu,
)

log = logging.getLogger("workers.cluster")


def read_resources() -> ClusterResources:
    """The connected cluster's resources now: totals, free, each live node's CPUs, and the
    autoscaler's limits."""
    import ray

    return ClusterResources(
        total=dict(ray.cluster_resources()),
        available=dict(ray.available_resources()),
        node_cpus=tuple(n["Resources"].get("CPU", 0.0) for n in ray.nodes() if n["Alive"]),
        autoscaler=autoscaler_limits(),
    )


def autoscaler_limits() -> dict[str, float]:
    """The most of each resource the autoscaler may grow the cluster to; empty where no autoscaler
    reports one (a fixed cluster) or the driver cannot ask (through Ray Client, or a Ray without
    the call)."""
    import ray

    try:
        from ray._private.state import state  # no public call reports the autoscaler's limits

        return dict(state.get_max_resources_from_cluster_config() or {})
    except (ImportError, AttributeError, ray.exceptions.RaySystemError):
        return {}


def cluster_layout(options: PipelineOptions, wait: float = FREE_GPU_WAIT_S) -> Layout:
    """The layout of a run on the connected cluster (`workers.sizing.plan_layout`). A run that
    sizes its GPU actors from the free GPUs and finds none waits up to `wait` seconds for one:
    actors that are ending give theirs back within seconds."""
    resources = read_resources()
    deadline = time.monotonic() + wait
    while waits_for_gpu(options, resources) and time.monotonic() < deadline:
        time.sleep(0.5)
        resources = read_resources()
    return plan_layout(options, resources)


def connect(address: str | None) -> None:
    """Join the cluster at `address` (or RAY_ADDRESS); start a local Ray when there is none."""
    import ray

    if ray.is_initialized():
        return
    address = address or os.environ.get("RAY_ADDRESS")
    if address:
        ray.init(address=address, log_to_driver=True)
    else:
        ray.init(include_dashboard=False)
    res = ray.cluster_resources()
    log.info(
        "Ray cluster: %d nodes, %g CPUs, %g GPUs",
        len(ray.nodes()),
        res.get("CPU", 0),
        res.get("GPU", 0),
    )
