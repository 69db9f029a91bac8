"""Cluster sizing as a pure function of what the cluster offers: no Ray cluster is started."""

from __future__ import annotations

import subprocess
import sys

import pytest

from workers.sizing import (
    ClusterCapacityError,
    ClusterResources,
    Layout,
    PipelineOptions,
    cpu_layout,
    free_gpu_actors,
    plan_layout,
    replica_gpus,
    waits_for_gpu,
)


def resources(
    total: dict[str, float],
    available: dict[str, float] | None = None,
    nodes: tuple[float, ...] | None = None,
    autoscaler: dict[str, float] | None = None,
) -> ClusterResources:
    """A snapshot: free defaults to the totals, the nodes to one holding every CPU."""
    return ClusterResources(
        total=total,
        available=dict(total) if available is None else available,
        node_cpus=(total.get("CPU", 0.0),) if nodes is None else nodes,
        autoscaler=autoscaler or {},
    )


def test_a_two_core_cpu_cluster_gets_one_single_threaded_actor_per_free_cpu():
    two = resources({"CPU": 2.0})
    assert cpu_layout(PipelineOptions(), two) == (2, 0.75)
    assert cpu_layout(PipelineOptions(actors=1), two) == (1, 1.5)
    assert cpu_layout(PipelineOptions(actors=3, actor_cpus=0.5), two) == (3, 0.5)
    assert cpu_layout(PipelineOptions(read_cpus=0.5, write_cpus=0.5), two) == (1, 1.0)
    assert plan_layout(PipelineOptions(), two) == Layout("cpu", 2, 0.75, 2, 2)
    assert plan_layout(PipelineOptions(actors=3, actor_cpus=0.5), two).readers == 3


def test_cpu_actors_fit_the_largest_node_and_what_others_leave_free():
    """Three nodes of 8, 16 and 4 cores: actors fill the 16-core node, less a reader and a writer;
    with 7 of its cores held by other actors (Serve replicas, say), the free 9 are shared."""
    cluster = resources({"CPU": 28.0}, nodes=(8.0, 16.0, 4.0))
    assert plan_layout(PipelineOptions(), cluster) == Layout("cpu", 16, 0.75, 16, 16)
    busy = resources({"CPU": 28.0}, {"CPU": 9.0}, nodes=(8.0, 16.0, 4.0))
    assert cpu_layout(PipelineOptions(), busy) == (9, 0.75)
    full = resources({"CPU": 2.0}, {"CPU": 0.0})
    assert cpu_layout(PipelineOptions(), full) == (1, 0.25), "one actor, the smallest share"


def test_gpu_clusters_get_one_actor_per_free_gpu_and_readers_from_the_free_cores():
    node = resources({"CPU": 16.0, "GPU": 1.0})
    assert plan_layout(PipelineOptions(), node) == Layout("gpu", 1, 0.5, 13, 2)
    pods = resources({"CPU": 36.0, "GPU": 4.0}, nodes=(4.0, 8.0, 8.0, 8.0, 8.0))
    assert plan_layout(PipelineOptions(), pods) == Layout("gpu", 4, 0.5, 29, 5)
    given = plan_layout(PipelineOptions(actors=2, actor_cpus=1.0), pods)
    assert given == Layout("gpu", 2, 1.0, 29, 5)
    assert plan_layout(PipelineOptions(use_gpu=False), node).model == "cpu"


def test_a_busy_gpu_cluster_sizes_from_the_gpus_left_and_fails_naming_the_numbers():
    held = resources({"CPU": 16.0, "GPU": 2.0}, {"CPU": 15.0, "GPU": 1.0})
    assert plan_layout(PipelineOptions(), held).actors == 1
    assert not waits_for_gpu(PipelineOptions(), held)
    none_free = resources({"CPU": 16.0, "GPU": 2.0}, {"CPU": 14.0, "GPU": 0.0})
    assert waits_for_gpu(PipelineOptions(), none_free)
    assert not waits_for_gpu(PipelineOptions(actors=1), none_free), "a named count waits on Ray"
    with pytest.raises(ClusterCapacityError, match=r"none of the Ray cluster's 2 GPU\(s\)"):
        plan_layout(PipelineOptions(), none_free)
    assert plan_layout(PipelineOptions(actors=2), none_free).actors == 2


def test_an_autoscaling_cluster_waits_for_gpus_it_can_add():
    """GPUs all held but the autoscaler can grow the GPU group: one actor waits for a new GPU. A
    cluster with no GPU yet runs CPU actors, while a Serve replica asks for a GPU there."""
    held = resources({"CPU": 8.0, "GPU": 2.0}, {"CPU": 6.0, "GPU": 0.0}, autoscaler={"GPU": 8.0})
    assert free_gpu_actors(held) == 1
    assert plan_layout(PipelineOptions(), held) == Layout("gpu", 1, 0.5, 3, 2)
    no_gpu_yet = resources({"CPU": 4.0}, autoscaler={"CPU": 68.0, "GPU": 8.0})
    assert plan_layout(PipelineOptions(), no_gpu_yet).model == "cpu"
    with pytest.raises(ValueError, match="has no GPU"):
        plan_layout(PipelineOptions(use_gpu=True), no_gpu_yet)
    assert replica_gpus("auto", no_gpu_yet) == 1.0
    assert replica_gpus("auto", resources({"CPU": 4.0})) == 0.0
    assert replica_gpus("auto", resources({"CPU": 4.0, "GPU": 1.0})) == 1.0
    assert replica_gpus("cuda", ClusterResources()) == 1.0
    assert replica_gpus("cpu", no_gpu_yet) == 0.0


def test_sizing_imports_without_ray():
    code = "import sys, workers.sizing; print('ray' in sys.modules)"
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert run.stdout.strip() == "False"
