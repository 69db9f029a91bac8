"""A two-node cluster on one machine with logical GPUs: one model actor per GPU, a GPU node that
leaves mid-job without costing a scan, and jobs beside a gateway's pool that holds GPUs.

The actors are scheduled on the logical GPUs (one each) but run their network on the CPU
(`device="cpu"`), so the tests behave the same on a host with a real GPU.
"""

from __future__ import annotations

import threading
import time
from dataclasses import replace

import pytest
from workers_helpers import build_tree, small_weights, tree_bytes

from rangeret.cli import main as rangeret_main
from rangeret.inference import PredictorSpec, checkpoint_profile
from rangeret.layout import discover
from workers.pipeline import PipelineOptions, run_pipeline

pytestmark = pytest.mark.slow


@pytest.fixture
def cluster():
    ray = pytest.importorskip("ray")
    from ray.cluster_utils import Cluster

    if ray.is_initialized():
        ray.shutdown()
    c = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
    nodes = [c.add_node(num_cpus=1, num_gpus=1) for _ in range(2)]
    c.wait_for_nodes()
    ray.init(address=c.address, log_to_driver=False)
    yield c, nodes
    ray.shutdown()
    c.shutdown()


def _spec(weights) -> PredictorSpec:
    return PredictorSpec(checkpoint=str(weights), height=32, width=256, device="cpu")


def _job(weights, data, out, **options):
    spec = _spec(weights)
    _, profile = checkpoint_profile(spec)
    entries = discover(data, ["08", "11"]).scans
    return run_pipeline(
        spec, profile, entries, out, PipelineOptions(read_cpus=0.25, write_cpus=0.1, **options)
    )


def _predict_here(weights, data, out) -> None:
    """`rangeret predict` in this process: the labels every Ray run must equal."""
    argv = ["predict", "-q", "--dataset", str(data), "--out", str(out), "--sequences", "08", "11"]
    net = ["--checkpoint", str(weights), "--height", "32", "--width", "256", "--device", "cpu"]
    assert rangeret_main([*argv, *net]) == 0


def _wait_for_free_gpus(count: int) -> None:
    """Until the cluster's view shows `count` GPUs free (actors take and give them back
    asynchronously)."""
    import ray

    deadline = time.monotonic() + 60
    while ray.available_resources().get("GPU", 0) != count and time.monotonic() < deadline:
        time.sleep(0.2)
    assert ray.available_resources().get("GPU", 0) == count


def test_one_model_actor_per_gpu_and_a_node_leaving(cluster, tmp_path):
    c, nodes = cluster
    weights = small_weights(tmp_path)
    data = build_tree(tmp_path / "data", labelled=3, unlabelled=5)
    _predict_here(weights, data, tmp_path / "single")

    result = _job(weights, data, tmp_path / "a")
    assert result.actors == 2
    assert len(result.devices) == 2, result.devices
    assert all(d.startswith("cpu@") for d in result.devices), result.devices
    assert not result.failed and result.written == 8
    assert tree_bytes(tmp_path / "a") == tree_bytes(tmp_path / "single")

    out = tmp_path / "b"
    done_at_removal: list[int] = []

    def remove_when_started() -> None:
        deadline = time.time() + 120
        while time.time() < deadline and not list(out.rglob("*.label")):
            time.sleep(0.05)
        done_at_removal.append(len(list(out.rglob("*.label"))))
        c.remove_node(nodes[1])

    remover = threading.Thread(target=remove_when_started, daemon=True)
    remover.start()
    result = _job(weights, data, out)
    remover.join(timeout=10)
    assert done_at_removal and done_at_removal[0] < 8, "the node left after the job, not during it"
    assert not result.failed and result.written == 8
    assert tree_bytes(out) == tree_bytes(tmp_path / "single")


def test_more_gpu_actors_than_gpus_is_a_named_error_not_a_hang(cluster, tmp_path):
    from workers.pipeline import ClusterCapacityError

    weights = small_weights(tmp_path)
    data = build_tree(tmp_path / "data", labelled=1, unlabelled=1)
    spec = _spec(weights)
    _, profile = checkpoint_profile(spec)
    options = PipelineOptions(actors=3, read_cpus=0.25, write_cpus=0.1, actor_start_timeout=10)
    with pytest.raises(
        ClusterCapacityError, match=r"3 model actor.*did not start within 10 s.*1 GPU"
    ):
        run_pipeline(
            spec,
            profile,
            discover(data, ["08", "11"]).scans,
            tmp_path / "out",
            options,
        )
    assert not list((tmp_path / "out").rglob("*.label"))


def test_a_job_runs_on_the_gateways_actors_that_hold_every_gpu(cluster, tmp_path):
    """The gateway's pool holds one actor per GPU: a job that starts its own actors fails at once
    with the numbers (the cluster cannot grow), and one given the pool's actors finishes."""
    from service.jobs import RayExecutor
    from workers.pipeline import ClusterCapacityError
    from workers.pool import ScanPool

    weights = small_weights(tmp_path)
    data = build_tree(tmp_path / "data", labelled=2, unlabelled=3)
    _predict_here(weights, data, tmp_path / "single")
    spec = _spec(weights)
    _, profile = checkpoint_profile(spec)
    entries = discover(data, ["08", "11"]).scans
    pool = ScanPool(replace(spec, profile=profile))
    try:
        infos = pool.wait_ready(timeout=120)
        assert pool.use_gpu and [i["device"] for i in infos] == ["cpu", "cpu"]
        _wait_for_free_gpus(0)
        with pytest.raises(ClusterCapacityError, match=r"none of the Ray cluster's 2 GPU\(s\)"):
            _job(weights, data, tmp_path / "own", actor_start_timeout=20)

        options = PipelineOptions(read_cpus=0.25, write_cpus=0.1, actor_start_timeout=20)
        out = tmp_path / "on-pool"
        result = run_pipeline(spec, profile, entries, out, options, model_actors=pool.actors)
        assert not result.failed and result.written == len(entries) == 5
        assert result.actors == 2 and {d.split("@")[0] for d in result.devices} == {"cpu"}
        assert tree_bytes(out) == tree_bytes(tmp_path / "single")

        executor = RayExecutor(spec, profile, pool=pool)
        done: list[tuple[int, int, int]] = []
        failed = executor.predict(
            entries,
            data,
            ["08", "11"],
            tmp_path / "job",
            lambda *counts: done.append(counts),
            threading.Event(),
        )
        assert failed == {} and done[-1] == (5, 0, 5)
        assert tree_bytes(tmp_path / "job") == tree_bytes(tmp_path / "single")
        assert executor.precision == "fp32"
    finally:
        pool.shutdown()


def test_a_job_takes_the_gpus_the_gateway_leaves(cluster, tmp_path):
    """A gateway started with fewer actors than GPUs: a job sizes its actors from the free GPUs."""
    from workers.pool import ScanPool

    weights = small_weights(tmp_path)
    data = build_tree(tmp_path / "data", labelled=1, unlabelled=3)
    pool = ScanPool(_spec(weights), actors=1)
    try:
        pool.wait_ready(timeout=120)
        _wait_for_free_gpus(1)
        result = _job(weights, data, tmp_path / "out", actor_start_timeout=20)
        assert result.actors == 1 and len(result.devices) == 1
        assert not result.failed and result.written == 4
        assert result.readers >= 2 and result.writers >= 2
    finally:
        pool.shutdown()
