"""A two-node cluster on one machine with logical GPUs: one model actor per GPU, a GPU node that
leaves mid-job without costing a scan, and jobs beside other actors (Serve replicas) that hold
GPUs.

The actors are scheduled on the logical GPUs (one each) but run their network on the CPU
(`device="cpu"`), so the tests behave the same on a host with a real GPU.
"""

from __future__ import annotations

import threading
import time

import pytest

from rangeret.cli.main import main as rangeret_main
from rangeret.dataset.layout import KITTI_LAYOUT, discover
from rangeret.inference.loaded_weights import load_weights
from rangeret.inference.spec import InferenceSpec
from tests.support.workers import build_tree, small_weights, tree_bytes
from workers.pipeline import run_pipeline
from workers.sizing import PipelineOptions

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


def _spec(weights) -> InferenceSpec:
    return InferenceSpec(checkpoint=str(weights), height=32, width=256, device="cpu")


def _job(weights, data, out, **options):
    spec = _spec(weights)
    profile = load_weights(spec).profile
    entries = discover(data, ["08", "11"], layout=KITTI_LAYOUT).scans
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

    run = _job(weights, data, tmp_path / "a")
    assert run.layout.actors == 2
    assert len(run.devices) == 2, run.devices
    assert all(d.startswith("cpu@") for d in run.devices), run.devices
    pids = ", ".join(d.split("@")[1] for d in run.devices)
    assert run.actors_text() == f"cpu (2 model actors: processes {pids})"
    assert not run.summary.failed and run.summary.written == 8
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
    run = _job(weights, data, out)
    remover.join(timeout=10)
    assert done_at_removal and done_at_removal[0] < 8, "the node left after the job, not during it"
    assert not run.summary.failed and run.summary.written == 8
    assert tree_bytes(out) == tree_bytes(tmp_path / "single")


def test_more_gpu_actors_than_gpus_is_a_named_error_not_a_hang(cluster, tmp_path):
    from workers.sizing import ClusterCapacityError

    weights = small_weights(tmp_path)
    data = build_tree(tmp_path / "data", labelled=1, unlabelled=1)
    spec = _spec(weights)
    profile = load_weights(spec).profile
    options = PipelineOptions(actors=3, read_cpus=0.25, write_cpus=0.1, actor_start_timeout=10)
    with pytest.raises(
        ClusterCapacityError, match=r"3 model actor.*did not start within 10 s.*1 GPU"
    ):
        run_pipeline(
            spec,
            profile,
            discover(data, ["08", "11"], layout=KITTI_LAYOUT).scans,
            tmp_path / "out",
            options,
        )
    assert not list((tmp_path / "out").rglob("*.label"))


def test_a_job_takes_the_gpus_other_actors_leave(cluster, tmp_path):
    """An actor holds one of the two GPUs (as a Serve replica does): a job sizes its model actors
    from the free GPUs, and one that finds none free says so with the numbers."""
    import ray

    from workers.sizing import ClusterCapacityError

    @ray.remote(num_gpus=1, num_cpus=0)
    class Replica:
        def ready(self) -> bool:
            return True

    weights = small_weights(tmp_path)
    data = build_tree(tmp_path / "data", labelled=1, unlabelled=3)
    holders = [Replica.remote()]
    try:
        ray.get(holders[0].ready.remote(), timeout=120)
        _wait_for_free_gpus(1)
        run = _job(weights, data, tmp_path / "out", actor_start_timeout=20)
        assert run.layout.actors == 1 and len(run.devices) == 1
        assert not run.summary.failed and run.summary.written == 4
        assert run.layout.readers >= 2 and run.layout.writers >= 2
        holders.append(Replica.remote())
        ray.get(holders[1].ready.remote(), timeout=120)
        _wait_for_free_gpus(0)
        with pytest.raises(ClusterCapacityError, match=r"none of the Ray cluster's 2 GPU\(s\)"):
            _job(weights, data, tmp_path / "none", actor_start_timeout=20)
    finally:
        for holder in holders:
            ray.kill(holder)


def test_the_model_actors_are_named_by_device_and_process_for_people():
    from workers.pipeline import PipelineRun

    run = PipelineRun(summary=None, evaluator=None, devices=["cuda:1@20", "cpu@7", "cuda:1@21"])  # type: ignore[arg-type]
    assert run.actors_text() == (
        "cpu (1 model actor: process 7), cuda:1 (2 model actors: processes 20, 21)"
    )
    assert PipelineRun(summary=None, evaluator=None).actors_text() == "no model actor"  # type: ignore[arg-type]
