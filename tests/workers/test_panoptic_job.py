"""`python -m workers.predict_job --panoptic` on a local Ray: the files, report and archive of
`rangeret predict --panoptic`, `evaluate --panoptic` and `submission --task panoptic`, on a
simulated SemanticKITTI tree (32 beams, random 20-class weights at 32 x 256, so that thing classes
and objects occur) and on a simulated nuScenes tree."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from rangeret.cli.main import main as rangeret_main
from rangeret.dataset.layout import ScanEntry
from rangeret.dataset.profiles import load_profile
from rangeret.evaluation.counting import RawLabelEvaluator
from rangeret.exceptions import InputError
from rangeret.inference.spec import InferenceSpec
from rangeret.io.panoptic_labels import PANOPTIC_NPZ, THOUSANDS, write_panoptic_npz
from rangeret.models import build_model
from tests.support.workers import tree_bytes
from workers.predict_job import main as job_main
from workers.stages import BatchRecord, write_results

NET = ["--height", "32", "--width", "256", "--device", "cpu"]


def _random_network(num_classes: int, seed: int = 3) -> dict[str, torch.Tensor]:
    """A 1-block network's state_dict with random weights, wide enough that the argmax varies
    from pixel to pixel (BatchNorm variances kept)."""
    net = build_model("rangeret-cir", 32, 256, num_classes=num_classes, layers=1).eval()
    g = torch.Generator().manual_seed(seed)
    return {
        k: torch.randn(v.shape, generator=g) * 0.5
        if v.is_floating_point() and not k.endswith("running_var")
        else v
        for k, v in net.state_dict().items()
    }


@pytest.fixture(scope="module")
def kitti(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """Two labelled scans of sequence 08 and one of test sequence 11, and the weights."""
    root = tmp_path_factory.mktemp("kitti")
    args = ["simulate", "-q", "--out", str(root / "data"), "--sequences", "08:2", "11:1"]
    assert (
        rangeret_main([*args, "--unlabelled", "11", "--beams", "32", "--azimuth-steps", "512"]) == 0
    )
    torch.save(_random_network(20), root / "w.pt")
    return root / "data", root / "w.pt"


@pytest.mark.slow
def test_the_panoptic_job_writes_what_rangeret_predict_writes(ray_local, kitti, tmp_path, capsys):
    """Byte for byte the files of `predict --panoptic`, whose low 16 bits are a semantic run's;
    the report is `evaluate --panoptic`'s, the archive the panoptic benchmark's."""
    data, weights = kitti
    args = ["-q", "--dataset", str(data), "--sequences", "08", "11", "--checkpoint", str(weights)]
    args += NET
    for name, extra in (("single", ["--panoptic"]), ("semantic", [])):
        assert rangeret_main(["predict", *args, "--out", str(tmp_path / name), *extra]) == 0
    report, archive = tmp_path / "report.json", tmp_path / "s.zip"
    job = [*args, "--out", str(tmp_path / "ray"), "--actors", "1", "--read-cpus", "0.25"]
    job += ["--panoptic", "--report", str(report), "--submission", str(archive), "--allow-partial"]
    assert job_main(job) == 0
    single, distributed = tree_bytes(tmp_path / "single"), tree_bytes(tmp_path / "ray")
    assert len(single) == 3 and single == distributed
    semantic = tree_bytes(tmp_path / "semantic")
    assert sorted(semantic) == sorted(distributed)
    objects = 0
    for name, written in distributed.items():
        labels = np.frombuffer(written, "<u4")
        assert np.array_equal(labels & 0xFFFF, np.frombuffer(semantic[name], "<u4"))
        objects += np.unique(labels >> 16).size - 1
    assert objects > 3, "the scans hold objects"

    scored = tmp_path / "evaluate.json"
    evaluate = ["evaluate", "-q", "--dataset", str(data), "--predictions", str(tmp_path / "ray")]
    assert rangeret_main([*evaluate, "--sequences", "08", "--panoptic", "--json", str(scored)]) == 0
    assert json.loads(report.read_text()) == json.loads(scored.read_text())
    assert json.loads(report.read_text())["benchmark"] == "semantickitti-panoptic"
    printed = capsys.readouterr().out
    assert "PQ-dagger" in printed and "semantickitti-panoptic rules" in printed

    validate = ["validate-submission", "-q", str(archive), "--dataset", str(data)]
    assert rangeret_main([*validate, "--allow-partial", "--task", "panoptic"]) == 0
    with zipfile.ZipFile(archive) as zf:
        member = "sequences/11/predictions/000000.label"
        assert zf.read(member) == distributed[member]
    run = json.loads((tmp_path / "ray" / "run.json").read_text())
    assert run["panoptic"] == {"angle": 10.0, "min_points": 10}
    assert run["runner"] == "workers.predict_job"

    capsys.readouterr()
    assert job_main(job) == 0, "resumed"
    assert "0 written, 3 already done, 0 failed" in capsys.readouterr().out
    semantic_job = [a for a in job if a not in ("--panoptic", "--report", str(report))]
    assert job_main(semantic_job) == 1
    assert "holds panoptic predictions and this run is semantic" in capsys.readouterr().err
    assert tree_bytes(tmp_path / "ray") == single


@pytest.mark.slow
def test_panoptic_in_the_inference_spec_writes_nuscenes_panoptic_files(ray_local, tmp_path, capsys):
    """`"panoptic": true` in --inference-spec (a gateway's job) chooses the panoptic files and
    benchmark as --panoptic does: nuScenes-panoptic's `.npz` files, byte for byte those of
    `rangeret predict --panoptic`, scored and archived for nuScenes-panoptic."""
    from rangeret.dataset.selection import DatasetSelection
    from rangeret.models import save_checkpoint
    from tests.support.nuscenes import network, small_profile, write_tree
    from workers.demo import _range_image_png

    data = write_tree(tmp_path / "nu", {"scene-0103": 2, "scene-0916": 1})
    weights = tmp_path / "w.pt"
    save_checkpoint(weights, network(), profile=small_profile().to_dict())
    args = ["-q", "--dataset", str(data), "--split", "mini_val"]
    net = ["--checkpoint", str(weights), "--device", "cpu"]
    assert (
        rangeret_main(["predict", *args, *net, "--panoptic", "--out", str(tmp_path / "one")]) == 0
    )
    spec = {"checkpoint": str(weights), "device": "cpu", "panoptic": True}
    report, archive = tmp_path / "report.json", tmp_path / "sub.zip"
    job = [*args, "--inference-spec", json.dumps(spec), "--out", str(tmp_path / "ray")]
    assert job_main([*job, "--report", str(report), "--submission", str(archive)]) == 0

    def panoptic_files(root: Path) -> dict[str, bytes]:
        return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*_panoptic.npz")}

    single, distributed = panoptic_files(tmp_path / "one"), panoptic_files(tmp_path / "ray")
    assert len(single) == 3 and single == distributed
    assert all(name.startswith("panoptic/mini_val/") for name in distributed)
    assert not (tmp_path / "ray" / "lidarseg").exists()

    scored = tmp_path / "evaluate.json"
    evaluate = ["evaluate", "-q", "--profile", "nuscenes", "--dataset", str(data)]
    evaluate += ["--predictions", str(tmp_path / "ray"), "--split", "mini_val", "--panoptic"]
    assert rangeret_main([*evaluate, "--json", str(scored)]) == 0
    result = json.loads(report.read_text())
    assert result == json.loads(scored.read_text())
    assert result["benchmark"] == "nuscenes-panoptic" and result["num_scans"] == 3
    validate = ["validate-submission", "-q", str(archive), "--profile", "nuscenes"]
    validate += ["--dataset", str(data), "--split", "mini_val", "--task", "panoptic"]
    assert rangeret_main(validate) == 0
    with zipfile.ZipFile(archive) as zf:
        assert sorted(n for n in zf.namelist() if n.endswith(".npz")) == sorted(distributed)

    # The demo's range image reads the classes of panoptic files.
    profile = load_profile("nuscenes")
    selection = DatasetSelection(data, ("scene-0103",), profile.layout, "mini_val", panoptic=True)
    png = _range_image_png(selection, tmp_path / "ray", profile, tmp_path / "range.png")
    assert png.read_bytes()[:4] == b"\x89PNG"
    capsys.readouterr()


def test_a_profile_without_thing_classes_is_refused_before_any_work(tmp_path, capsys):
    """The job in one line, before its output folder exists; the pipeline before any actor."""
    from workers.pipeline import run_pipeline

    torch.manual_seed(0)
    network = build_model("rangeret-cir", 64, 128, num_classes=15, layers=1)
    torch.save(network.state_dict(), tmp_path / "w.pt")
    net = ["--checkpoint", str(tmp_path / "w.pt"), "--width", "128", "--profile", "pandaset"]
    out = tmp_path / "pred"
    args = ["-q", "--dataset", str(tmp_path), "--sequences", "3", "--out", str(out), *net]
    assert job_main([*args, "--panoptic"]) == 1
    assert "the pandaset profile names no thing classes" in capsys.readouterr().err
    assert not out.exists()
    with pytest.raises(InputError, match="names no thing classes"):
        run_pipeline(InferenceSpec(panoptic=True), load_profile("pandaset"), [], out)


def test_the_writer_counts_the_semantic_part_of_panoptic_labels(tmp_path):
    """nuScenes-panoptic labels (1000 x class + instance) count as their classes, as the labels
    of a semantic prediction would."""
    profile = load_profile("nuscenes")
    rng = np.random.default_rng(0)
    raw_gt, raw_pred = rng.integers(0, 32, (2, 500)).astype(np.uint32)
    instances = rng.integers(0, 4, 500).astype(np.uint32)
    truth = tmp_path / "truth_panoptic.npz"
    write_panoptic_npz(truth, THOUSANDS.encode(raw_gt, instances, raw_gt))
    entry = ScanEntry(
        "scene-0103",
        "token",
        tmp_path / "token.pcd.bin",
        truth,
        "panoptic/mini_val/token_panoptic.npz",
        "confidence/mini_val/token.npy",
        PANOPTIC_NPZ,
    )
    bands = np.zeros(500, np.uint8)
    labels = THOUSANDS.encode(raw_pred, instances, raw_pred)
    record = BatchRecord(0, [entry], results=[(labels, None)], bands=[bands])
    written = write_results(record, str(tmp_path / "out"), profile, panoptic=True)
    assert written.failures == [None] and written.points == 500
    assert np.array_equal(PANOPTIC_NPZ.read(tmp_path / "out" / entry.prediction), labels)
    expected = RawLabelEvaluator.for_profile(profile)
    expected.add(raw_pred, raw_gt, "scene-0103", bands)
    assert written.counts is not None
    assert np.array_equal(written.counts.confusion().matrix, expected.confusion().matrix)
    assert expected.confusion().matrix.sum() > 0
