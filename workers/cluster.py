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
from typing import Any

from workers.sizing import (
    FREE_GPU_WAIT_S,
    ClusterResources,
    Layout,
    PipelineOptions,
    plan_layout,
    waits_for_gpu,
)

log = logging.getLogger("workers.cluster")

#: Set to 0, a Ray started here registers its node on loopback and its processes listen there
#: only (Ray's switch for machines that run no multi-node cluster, read when Ray is imported).
LOOPBACK_VARIABLE = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"


def session_folder() -> str:
    """The temp folder of a Ray this process starts: its own, and short, since Ray's socket
    paths under it must stay within the 107 bytes a Unix socket's path may have."""
    return f"/tmp/rangeret-ray-{os.getpid()}"


def start_local(**options: Any) -> Any:
    """Start a Ray of this machine alone (`ray.init` with `options`, no dashboard unless they
    say otherwise) on loopback, in `session_folder()`; its context. A warning says so where Ray
    still registered its node on another address."""
    import ray
    from ray._private import ray_constants  # the switch, where Ray was imported before it was set

    before = os.environ.get(LOOPBACK_VARIABLE)
    os.environ[LOOPBACK_VARIABLE] = "0"  # for the processes Ray starts
    switch = ray_constants.ENABLE_RAY_CLUSTER
    ray_constants.ENABLE_RAY_CLUSTER = False  # for this process's own node address
    try:
        context = ray.init(**{"include_dashboard": False, "_temp_dir": session_folder(), **options})
    finally:
        ray_constants.ENABLE_RAY_CLUSTER = switch
        if before is None:
            del os.environ[LOOPBACK_VARIABLE]
        else:
            os.environ[LOOPBACK_VARIABLE] = before
    address = ray.util.get_node_ip_address()
    if address not in ("127.0.0.1", "::1"):
        log.warning(
            "the local Ray registered its node on %s and listens on that interface too", address
        )
    return context


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
    """Join the cluster at `address` (or RAY_ADDRESS); start a local Ray when there is none, on
    loopback and in a session folder of its own (`start_local`)."""
    address = address or os.environ.get("RAY_ADDRESS")
    import ray

    if ray.is_initialized():
        return
    if address:
        ray.init(address=address, log_to_driver=True)
    else:
        start_local()
    res = ray.cluster_resources()
    log.info(
        "Ray cluster: %d nodes, %g CPUs, %g GPUs",
        len(ray.nodes()),
        res.get("CPU", 0),
        res.get("GPU", 0),
    )
