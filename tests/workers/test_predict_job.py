"""The Ray pipeline on a local Ray: same labels as `rangeret predict`, resume, and a model actor
killed mid-run; the single-scan worker that Serve replicas and the in-process gateway run."""

from __future__ import annotations

import json
import time
import zipfile

import pytest
import torch

from rangeret.cli.main import main as rangeret_main
from rangeret.dataset.layout import KITTI_LAYOUT
from rangeret.inference.spec import InferenceSpec
from rangeret.io.scans import read_scan
from tests.support.workers import build_tree, kill_actor_when, small_weights, tree_bytes
from workers.predict_job import main as job_main

pytestmark = pytest.mark.slow

NET = ["--checkpoint", "{w}", "--height", "32", "--width", "256", "--device", "cpu"]


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    folder = tmp_path_factory.mktemp("workers")
    return build_tree(folder / "data", labelled=3, unlabelled=2), small_weights(folder)


def _net(weights, *extra):
    return [a.format(w=weights) for a in NET] + list(extra)


@pytest.mark.parametrize("batch", ["1", "2"])
def test_job_equals_rangeret_predict_and_evaluate(ray_local, setup, tmp_path, batch, capsys):
    data, weights = setup
    seqs = ["--sequences", "08", "11"]
    assert (
        rangeret_main(
            [
                "predict",
                "-q",
                "--dataset",
                str(data),
                "--out",
                str(tmp_path / "single"),
                *seqs,
                *_net(weights, "--batch-size", batch),
            ]
        )
        == 0
    )
    code = job_main(
        [
            "-q",
            "--dataset",
            str(data),
            "--out",
            str(tmp_path / "ray"),
            *seqs,
            "--report",
            str(tmp_path / "report.json"),
            "--actors",
            "1",
            "--read-cpus",
            "0.25",
            *_net(weights, "--batch-size", batch),
        ]
    )
    assert code == 0
    single, distributed = tree_bytes(tmp_path / "single"), tree_bytes(tmp_path / "ray")
    assert len(single) == 5 and single == distributed
    assert (
        rangeret_main(
            [
                "evaluate",
                "-q",
                "--dataset",
                str(data),
                "--predictions",
                str(tmp_path / "ray"),
                "--sequences",
                "08",
                "--json",
                str(tmp_path / "eval.json"),
            ]
        )
        == 0
    )
    job_report = json.loads((tmp_path / "report.json").read_text())
    eval_report = json.loads((tmp_path / "eval.json").read_text())
    assert job_report["confusion"] == eval_report["confusion"]
    assert job_report["miou"] == eval_report["miou"]
    assert job_report["precision"] == "fp32", "the default, as the CPU model actor ran it"
    assert job_report["backend"] == "torch"
    assert list(job_report["per_sequence"]) == ["08"]
    for key in ("per_sequence", "per_distance"):
        assert job_report[key] == eval_report[key]
    for name in ("iou.png", "iou-by-distance.png", "miou-by-sequence.png"):
        assert (tmp_path / "report-plots" / name).exists()
    runs = [json.loads((tmp_path / t / "run.json").read_text()) for t in ("single", "ray")]
    assert [r["runner"] for r in runs] == ["rangeret predict", "workers.predict_job"]
    assert sorted(runs[0]) == sorted(runs[1])
    same = ("model", "checkpoint_sha256", "projection", "knn", "tta", "batch_size", "sequences")
    assert all(runs[0][k] == runs[1][k] for k in same)
    capsys.readouterr()


def test_job_resumes_and_names_bad_scans(ray_local, setup, tmp_path, capsys):
    data, weights = setup
    args = [
        "-q",
        "--dataset",
        str(data),
        "--out",
        str(tmp_path / "p"),
        "--sequences",
        "08",
        "11",
        "--read-cpus",
        "0.25",
        *_net(weights),
        "--submission",
        str(tmp_path / "s.zip"),
        "--allow-partial",
        "--method-name",
        "RangeRet",
        "--code-url",
        "https://example.org/code",
    ]
    assert job_main(args) == 0
    first = tree_bytes(tmp_path / "p")
    with zipfile.ZipFile(tmp_path / "s.zip") as zf:
        lines = zf.read("description.txt").decode().splitlines()
    run = json.loads((tmp_path / "p" / "run.json").read_text())
    assert lines[:4] == [
        "name: RangeRet",
        "pdf url: n/a",
        "code url: https://example.org/code",
        f"checkpoint sha256: {run['checkpoint_sha256']}",
    ]
    assert "written by: workers.predict_job" in lines
    victim = tmp_path / "p" / "sequences" / "08" / "predictions" / "000001.label"
    victim.unlink()
    capsys.readouterr()
    assert job_main(args) == 0
    assert "1 written, 4 already done, 0 failed" in capsys.readouterr().out
    assert tree_bytes(tmp_path / "p") == first
    record = json.loads((tmp_path / "p" / "run.json").read_text())
    assert [r["runner"] for r in record["runs"]] == ["workers.predict_job"] * 2
    assert record["runs"][0]["started"] == run["started"] == run["runs"][0]["started"]
    assert record["runs"][1]["started"] == record["started"]

    bad = tmp_path / "bad"
    build_tree(bad, labelled=2, unlabelled=1)
    (bad / "sequences" / "11" / "velodyne" / "000002.bin").write_bytes(b"\x00" * 7)
    code = job_main(
        [
            "-q",
            "--dataset",
            str(bad),
            "--out",
            str(tmp_path / "q"),
            "--sequences",
            "08",
            "11",
            "--read-cpus",
            "0.25",
            *_net(weights),
        ]
    )
    out = capsys.readouterr()
    assert code == 1
    assert "FAILED 11/000002" in out.out and "multiple of 16" in out.out
    assert "1 of 3 scans could not be predicted" in out.err
    assert len(tree_bytes(tmp_path / "q")) == 2


def test_a_model_actor_killed_mid_run_costs_no_scan(ray_local, tmp_path, setup, capsys):
    _, weights = setup
    data = build_tree(tmp_path / "data", labelled=4, unlabelled=20)
    assert (
        rangeret_main(
            [
                "predict",
                "-q",
                "--dataset",
                str(data),
                "--out",
                str(tmp_path / "single"),
                "--sequences",
                "08",
                "11",
                *_net(weights),
            ]
        )
        == 0
    )
    out = tmp_path / "ray"
    killer = kill_actor_when(lambda: len(list(out.rglob("*.label"))) >= 1)
    code = job_main(
        [
            "-q",
            "--dataset",
            str(data),
            "--out",
            str(out),
            "--sequences",
            "08",
            "11",
            "--read-cpus",
            "0.25",
            *_net(weights),
        ]
    )
    killer.join(timeout=5)
    assert killer.killed, "no model actor was killed: the test did not exercise a crash"
    assert code == 0
    assert tree_bytes(out) == tree_bytes(tmp_path / "single")
    capsys.readouterr()


def test_a_job_runs_beside_actors_that_hold_cpus(ray_local, setup, tmp_path, capsys, caplog):
    """Regression: CPU model actors were sized from a node's total CPUs, so a job never started
    while other actors (Serve replicas, say) held some of them. Also: --allow-partial predicts
    the sequences of the split that the dataset holds, naming the others."""
    data, weights = setup

    @ray_local.remote(num_cpus=1)
    class Holder:
        def ready(self) -> bool:
            return True

    holder = Holder.remote()
    try:
        assert ray_local.get(holder.ready.remote(), timeout=120)
        code = job_main(
            [
                "-q",
                "--dataset",
                str(data),
                "--out",
                str(tmp_path / "p"),
                "--split",
                "test",
                "--allow-partial",
                *_net(weights),
            ]
        )
        assert code == 0 and sorted(tree_bytes(tmp_path / "p")) == [
            "sequences/11/predictions/000003.label",
            "sequences/11/predictions/000004.label",
        ]
        assert (
            "the test split's sequences 12, 13" in caplog.text and "; predicting 11" in caplog.text
        )
        assert json.loads((tmp_path / "p" / "run.json").read_text())["sequences"] == ["11"]
    finally:
        ray_local.kill(holder)
    capsys.readouterr()


def test_the_job_refuses_partial_splits_and_other_weights_before_it_starts(setup, tmp_path, capsys):
    """Both refusals come before Ray starts and before any scan or run record is written."""
    from rangeret.io.run_info import write_run_info

    data, weights = setup
    out = tmp_path / "p"
    base = ["-q", "--dataset", str(data), "--out", str(out), *_net(weights)]
    assert job_main([*base, "--split", "test"]) == 1
    err = capsys.readouterr().err
    assert "the test split's sequences 12, 13" in err and "--allow-partial" in err
    assert not out.exists()
    write_run_info(
        out,
        {"checkpoint_sha256": "c" * 64},
        runner="rangeret predict",
        dataset=data,
        sequences=["08"],
        batch_size=1,
    )
    before = (out / "run.json").read_bytes()
    assert job_main([*base, "--sequences", "08"]) == 1
    err = capsys.readouterr().err
    assert "cccccccccccc" in err and str(out) in err and "--overwrite" in err
    assert (out / "run.json").read_bytes() == before and tree_bytes(out) == {}


def test_cpu_layout_defaults_to_one_single_threaded_actor_per_free_cpu(ray_local):
    from workers.cluster import cluster_layout, read_resources
    from workers.sizing import Layout, PipelineOptions, cpu_layout

    deadline = time.monotonic() + 60  # actors of earlier tests give their CPUs back asynchronously
    while ray_local.available_resources().get("CPU", 0) < 2 and time.monotonic() < deadline:
        time.sleep(0.5)
    resources = read_resources()
    assert cpu_layout(PipelineOptions(), resources) == (2, 0.75)
    assert cpu_layout(PipelineOptions(actors=1), resources) == (1, 1.5)
    assert cpu_layout(PipelineOptions(actors=3, actor_cpus=0.5), resources) == (3, 0.5)
    assert cpu_layout(PipelineOptions(read_cpus=0.5, write_cpus=0.5), resources) == (1, 1.0)
    assert cluster_layout(PipelineOptions()) == Layout("cpu", 2, 0.75, 2, 2)
    assert cluster_layout(PipelineOptions(actors=3, actor_cpus=0.5)).readers == 3


def test_readers_and_writers_beside_gpu_actors_grow_with_the_free_cores():
    """A reader reads and projects a scan in about 20 ms of a core: a 16-core node with one GPU
    actor gets 13 of them (about 650 scans/s), a cluster of 4 such 8-core pods and a 4-core head
    29; small clusters keep 2 of each."""
    from workers.sizing import gpu_feeders

    assert gpu_feeders(16, 0.5) == (13, 2)
    assert gpu_feeders(36, 4 * 0.5) == (29, 5)
    assert gpu_feeders(3, 1.0) == (2, 2)
    assert gpu_feeders(0.5, 1.0) == (2, 2)


def test_model_actors_warm_up_before_their_first_batch(setup):
    """The pipeline's model actors and the single-scan worker run the network once when they are
    built: a real batch then finds every decay table made and builds none."""
    from rangeret.dataset.layout import discover
    from rangeret.inference.loaded_weights import load_weights
    from rangeret.inference.predictor import Predictor
    from rangeret.inference.scan_worker import ScanRequest, ScanWorker
    from rangeret.models.blocks.decay import GridCache
    from workers.stages import ROW_COLUMN, BatchRecord, ModelWorker, read_and_project

    data, weights = setup
    spec = InferenceSpec(checkpoint=str(weights), height=32, width=256, device="cpu")
    profile = load_weights(spec).profile
    record = BatchRecord(0, discover(data, ["08"], layout=KITTI_LAYOUT).scans[:2])
    row = read_and_project(record, profile.projection, points=profile.points).encode()[ROW_COLUMN]
    threads = torch.get_num_threads()
    try:
        model_worker = ModelWorker(spec, profile, 1.0)
        scan_worker = ScanWorker(Predictor.from_spec(spec))
    finally:
        torch.set_num_threads(threads)
    scans = [read_scan(e.scan_path) for e in record.entries]

    def through_model_worker() -> list:
        labelled = BatchRecord.decode(
            {ROW_COLUMN: model_worker({ROW_COLUMN: [row]})[ROW_COLUMN][0]}
        )
        return [error for _, error in labelled.results]

    def through_scan_worker() -> list:
        labelled = scan_worker.label_requests([ScanRequest(s) for s in scans])
        return [r if isinstance(r, str) else None for r in labelled]

    runs = [
        (model_worker.predictor, through_model_worker),
        (scan_worker.predictor, through_scan_worker),
    ]
    for predictor, run in runs:
        caches = [m for m in predictor.network.modules() if isinstance(m, GridCache)]
        built = [c.entries() for c in caches]
        assert caches and all(any(key[0] != "rotary" for key in b) for b in built), built
        assert run() == [None, None]
        after = [c.entries() for c in caches]
        assert [b.keys() for b in built] == [a.keys() for a in after]
        assert all(a[k] is b[k] for a, b in zip(after, built, strict=True) for k in b)
    assert model_worker.warm_up_seconds > 0 and scan_worker.warm_up_seconds > 0


def test_pandaset_scans_go_through_the_ray_job(ray_local, tmp_path, capsys):
    """5-float records, rows from laser ids, ROOT/NNN, class 0 car: the job equals rangeret
    predict, and its report ignores class 14."""
    from rangeret.dataset.profiles import load_profile
    from rangeret.models import build_model
    from rangeret.sim import SensorConfig, simulate_dataset

    profile = load_profile("pandaset")
    sensor = SensorConfig.for_profile(profile, azimuth_steps=256)
    data = tmp_path / "data"
    simulate_dataset(data, {"3": 2, "40": 1}, labelled=["3"], sensor=sensor, profile=profile)
    torch.manual_seed(0)
    network = build_model("rangeret-cir", 64, 128, num_classes=15, layers=1)
    torch.save(network.state_dict(), tmp_path / "w.pt")
    net = ["--checkpoint", str(tmp_path / "w.pt"), "--width", "128", "--profile", "pandaset"]
    args = ["-q", "--dataset", str(data), "--sequences", "3", "40", *net, "--device", "cpu"]
    assert rangeret_main(["predict", *args, "--out", str(tmp_path / "single")]) == 0
    report = tmp_path / "report.json"
    assert job_main([*args, "--out", str(tmp_path / "ray"), "--report", str(report)]) == 0
    single, distributed = tree_bytes(tmp_path / "single"), tree_bytes(tmp_path / "ray")
    assert len(single) == 3 and single == distributed
    assert sorted(p.name for p in (tmp_path / "ray" / "sequences").iterdir()) == ["003", "040"]
    result = json.loads(report.read_text())
    assert result["profile"] == "pandaset" and "unlabeled" not in result["iou"]
    assert len(result["iou"]) == 14
    capsys.readouterr()


def test_nuscenes_sweeps_go_through_the_ray_job(ray_local, tmp_path, capsys):
    """A version's tables, rows from the ring, challenge classes: the job writes the bytes
    rangeret predict writes, scores as the devkit, and its archive is the validated mini_val
    results folder."""
    from rangeret.models import save_checkpoint
    from tests.support.nuscenes import network, small_profile, write_tree

    data = write_tree(tmp_path / "nu", {"scene-0103": 2, "scene-0916": 1})
    save_checkpoint(tmp_path / "w.pt", network(), profile=small_profile().to_dict())
    args = ["-q", "--dataset", str(data), "--split", "mini_val"]
    args += ["--checkpoint", str(tmp_path / "w.pt"), "--device", "cpu"]
    assert rangeret_main(["predict", *args, "--out", str(tmp_path / "single")]) == 0
    report, archive = tmp_path / "report.json", tmp_path / "sub.zip"
    job = [*args, "--out", str(tmp_path / "ray"), "--report", str(report)]
    assert job_main([*job, "--submission", str(archive)]) == 0

    def lidarseg(root):
        return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*_lidarseg.bin")}

    single, distributed = lidarseg(tmp_path / "single"), lidarseg(tmp_path / "ray")
    assert len(single) == 3 and single == distributed
    assert all(name.startswith("lidarseg/mini_val/") for name in single)
    result = json.loads(report.read_text())
    assert result["profile"] == "nuscenes" and result["scoring"] == "nuscenes"
    assert "freq_weighted_iou" in result and "ignore" not in result["iou"]
    with zipfile.ZipFile(archive) as zf:
        names = zf.namelist()
    assert "mini_val/submission.json" in names
    assert sorted(n for n in names if n.endswith(".bin")) == sorted(single)
    capsys.readouterr()


def test_a_model_actor_refuses_a_checkpoint_other_than_the_drivers(setup, tmp_path):
    """The driver reads the checkpoint and passes its SHA-256 on: an actor that finds other
    bytes at the path (replaced after the driver read it) fails naming both, and the same
    bytes load."""
    from rangeret.inference.loaded_weights import WeightsChanged, load_weights
    from rangeret.models.weights.hub import file_sha256
    from workers.stages import ModelWorker

    _, weights = setup
    copy = tmp_path / "w.pt"
    copy.write_bytes(weights.read_bytes())
    spec = InferenceSpec(checkpoint=str(copy), height=32, width=256, device="cpu")
    profile = load_weights(spec).profile
    checked = file_sha256(copy)
    threads = torch.get_num_threads()
    try:
        assert ModelWorker(spec, profile, 1.0, checked).predictor is not None
        copy.write_bytes(weights.read_bytes()[:-1])
        with pytest.raises(
            WeightsChanged,
            match=rf"not the checkpoint of sha256 {checked[:16]} read by the job's driver",
        ):
            ModelWorker(spec, profile, 1.0, checked)
    finally:
        torch.set_num_threads(threads)
