"""The predictor and `rangeret predict`: one label per point, resumable, no scan lost."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch

from rangeret.cli.main import main
from rangeret.dataset.labels import semantickitti
from rangeret.dataset.layout import KITTI_LAYOUT, list_scans, prediction_path, velodyne_dir
from rangeret.dataset.projection import ProjectionConfig, project
from rangeret.dataset.selection import DatasetSelection
from rangeret.inference.loading import batches, load_batch, predict_loaded, project_scans
from rangeret.inference.predictor import Predictor
from rangeret.inference.results import RunSummary
from rangeret.inference.runtime.fast_graph import FastGraph
from rangeret.inference.settings import KnnSettings, TtaSettings
from rangeret.inference.timing import StageTimes
from rangeret.inference.tta import transformed_view
from rangeret.io.scans import KITTI_RECORD, read_labels, read_scan, write_scan
from rangeret.models import build_model
from tests.support.paths import load_vectors

VALID_RAW = np.array(semantickitti().class_raw_ids)


@pytest.fixture(scope="module")
def small_weights(tmp_path_factory):
    """The small published-layout state_dict (32 x 256, 2 blocks), saved alone like a release file."""
    fixture = load_vectors("rangeret-cir-32x256-2block.pt")
    path = tmp_path_factory.mktemp("weights") / "cir-small.pt"
    torch.save(fixture["state_dict"], path)
    return path


@pytest.fixture(scope="module")
def scan(real_scan_path):
    return read_scan(real_scan_path)


@pytest.fixture
def tree(tmp_path, scan):
    """Four subsampled variants of the real scan in two sequences."""
    root = tmp_path / "data"
    for i, (seq, step) in enumerate([("08", 7), ("08", 11), ("08", 13), ("42", 17)]):
        write_scan(
            velodyne_dir(root, seq, layout=KITTI_LAYOUT) / f"{i:06d}.bin",
            scan[i::step],
            record=KITTI_RECORD,
        )
    return root


@pytest.mark.slow
def test_predictor_on_the_real_scan_with_release_shaped_weights(tmp_path, scan):
    torch.manual_seed(0)  # the weights of benchmarks/bench_precision.py
    release = build_model("rangeret-cir", 64, 1024).state_dict()  # the release's 8-block shape
    torch.save(release, tmp_path / "kitti.pt")
    predictor = Predictor.from_checkpoint(tmp_path / "kitti.pt", device="cpu", precision="fp32")
    assert predictor.graph is None  # fp32 runs the network itself: the published labels exactly
    times = StageTimes()
    (first,) = predictor.label_projections([predictor.project(scan, times)], times)
    assert set(times.per_scan_ms()) == {"project", "network", "refine"}
    second = predictor.predict(scan)
    assert first.labels.shape == (len(scan),) and first.labels.dtype == np.uint32
    assert np.isin(first.labels, VALID_RAW).all()
    np.testing.assert_array_equal(first.labels, second.labels)
    # bf16 runs the inference graph, which labels nearly every point as fp32 does
    bf16 = Predictor.from_checkpoint(tmp_path / "kitti.pt", device="cpu", precision="bf16")
    assert bf16.graph.dtype == torch.bfloat16
    agree = np.mean(bf16.predict(scan).labels == first.labels)
    assert agree >= 0.999, agree


def test_bf16_on_the_cpu_runs_the_inference_graph(small_weights, scan):
    predictor = Predictor.from_checkpoint(
        small_weights, height=32, width=256, device="cpu", precision="bf16"
    )
    assert isinstance(predictor.graph, FastGraph) and predictor.graph.dtype == torch.bfloat16
    proj = predictor.project(scan[::5])
    logits = predictor.logits([proj])
    assert logits.dtype == torch.float32
    plain = Predictor.from_checkpoint(
        small_weights, height=32, width=256, device="cpu", precision="fp32"
    )
    assert plain.graph is None
    expected = plain.logits([proj])
    assert (logits.argmax(1) == expected.argmax(1)).float().mean().item() >= 0.97
    assert predictor.with_knn(None).graph is predictor.graph


def test_stages_compose_to_predict(small_weights, scan):
    predictor = Predictor.from_checkpoint(small_weights, height=32, width=256, device="cpu")
    pts = scan[::5]
    whole = predictor.predict(pts)
    proj = predictor.project(pts)
    logits = predictor.logits([proj])
    assert logits.shape == (1, 20, 32, 256) and logits.dtype == torch.float32
    [classes] = predictor.refine_batch([proj], logits)
    np.testing.assert_array_equal(predictor.to_raw(classes), whole.labels)


def test_without_knn_points_take_their_pixel_class_and_unprojected_get_zero(small_weights, scan):
    predictor = Predictor.from_checkpoint(
        small_weights, height=32, width=256, device="cpu", knn=None
    )
    pts = scan[::9].copy()
    pts[:3, :3] = 0.0
    result = predictor.predict(pts)
    assert result.labels[:3].tolist() == [0, 0, 0]
    proj = predictor.project(pts)
    pixel_classes = predictor.logits([proj])[0].argmax(0).numpy()
    np.testing.assert_array_equal(
        result.classes[3:], pixel_classes[proj.proj_y[3:], proj.proj_x[3:]]
    )


def test_batches_give_the_same_labels_as_single_scans(small_weights, scan):
    predictor = Predictor.from_checkpoint(small_weights, height=32, width=256, device="cpu")
    scans = [scan[::7], scan[1::9]]
    batched = predictor.label_projections([predictor.project(p) for p in scans])
    for pts, result in zip(scans, batched, strict=True):
        np.testing.assert_array_equal(predictor.predict(pts).labels, result.labels)


def test_tta_views_look_liketransformed_viewed_scans(scan):
    pts = scan[::3]
    base = torch.from_numpy(project(pts, 64, 1024).image)[None]
    mirrored = pts.copy()
    mirrored[:, 1] *= -1
    expected = torch.from_numpy(project(mirrored, 64, 1024).image)[None]
    view = transformed_view(base, True, 0, ProjectionConfig())
    same = (view - expected).abs().amax(dim=1) < 1e-3
    assert same.float().mean() > 0.9

    angle = -2 * np.pi * 256 / 1024
    rotated = pts.copy()
    rotated[:, 0] = np.cos(angle) * pts[:, 0] - np.sin(angle) * pts[:, 1]
    rotated[:, 1] = np.sin(angle) * pts[:, 0] + np.cos(angle) * pts[:, 1]
    expected = torch.from_numpy(project(rotated, 64, 1024).image)[None]
    view = transformed_view(base, False, 256, ProjectionConfig())
    same = (view - expected).abs().amax(dim=1) < 1e-3
    assert same.float().mean() > 0.9


def test_tta_runs_and_keeps_one_label_per_point(small_weights, scan):
    predictor = Predictor.from_checkpoint(
        small_weights, height=32, width=256, device="cpu", tta=TtaSettings(flip=True, shifts=1)
    )
    assert len(predictor.tta.views(256)) == 4
    result = predictor.predict(scan[::10])
    assert result.labels.shape == (len(scan[::10]),) and np.isin(result.labels, VALID_RAW).all()


def _predict_args(data, out, weights, *extra):
    return [
        "predict",
        "-q",
        "--dataset",
        str(data),
        "--out",
        str(out),
        "--checkpoint",
        str(weights),
        "--height",
        "32",
        "--width",
        "256",
        "--device",
        "cpu",
        *extra,
    ]


def test_predict_command_writes_resumes_and_names_bad_scans(tree, tmp_path, small_weights, capsys):
    out = tmp_path / "pred"
    assert main(_predict_args(tree, out, small_weights, "--sequences", "08", "42")) == 0
    files = sorted(out.rglob("*.label"))
    assert len(files) == 4
    for f in files:
        seq = f.parent.parent.name
        n = (
            velodyne_dir(tree, seq, layout=KITTI_LAYOUT) / f.name.replace(".label", ".bin")
        ).stat().st_size // 16
        labels = read_labels(f, num_points=n)
        assert np.isin(labels, VALID_RAW).all()
    assert "4 written, 0 already done, 0 failed" in capsys.readouterr().out
    assert (out / "run.json").exists()

    target = prediction_path(out, "08", "000001")
    before = {f: f.stat().st_mtime_ns for f in files if f != target}
    saved = target.read_bytes()
    target.unlink()
    assert main(_predict_args(tree, out, small_weights, "--sequences", "08", "42")) == 0
    assert "1 written, 3 already done" in capsys.readouterr().out
    assert target.read_bytes() == saved
    assert {f: f.stat().st_mtime_ns for f in before} == before

    (velodyne_dir(tree, "42", layout=KITTI_LAYOUT) / "000009.bin").write_bytes(b"\x01" * 30)
    for f in out.rglob("*.label"):
        f.unlink()
    code = main(
        _predict_args(tree, out, small_weights, "--sequences", "08", "42", "--batch-size", "2")
    )
    captured = capsys.readouterr()
    assert code == 1
    assert "1 of 5 scans could not be predicted" in captured.err
    assert "42/000009" in captured.out and "multiple of 16" in captured.out
    assert len(list(out.rglob("*.label"))) == 4


def test_predict_command_errors(tree, tmp_path, small_weights, capsys):
    assert main(_predict_args(tree, tmp_path / "p", small_weights, "--sequences", "07")) == 1
    assert "sequence 07 is missing" in capsys.readouterr().err
    (tmp_path / "junk.pt").write_bytes(b"junk")
    assert main(_predict_args(tree, tmp_path / "p", tmp_path / "junk.pt", "--split", "valid")) == 1
    assert "junk.pt is not a RangeRet checkpoint" in capsys.readouterr().err
    assert (
        main(
            _predict_args(
                tree, tmp_path / "p", small_weights, "--split", "valid", "--batch-size", "0"
            )
        )
        == 1
    )
    assert "--batch-size must be at least 1" in capsys.readouterr().err


def test_knn_settings_defaults_are_the_release_ones():
    assert KnnSettings() == KnnSettings(k=7, search=7, sigma=1.0, cutoff=1.0)


def test_each_run_reports_only_its_own_stage_times(tree, tmp_path, small_weights):
    from rangeret.inference.runner import predict_tree

    predictor = Predictor.from_checkpoint(small_weights, height=32, width=256, device="cpu")
    first = predict_tree(
        predictor,
        DatasetSelection.named(tree, ["08"], KITTI_LAYOUT),
        tmp_path / "a",
        progress=False,
    )
    second = predict_tree(
        predictor,
        DatasetSelection.named(tree, ["08", "42"], KITTI_LAYOUT),
        tmp_path / "b",
        progress=False,
    )
    assert first.times.scans["network"] == 3 and second.times.scans["network"] == 4
    assert second.times.scans["read"] == second.times.scans["write"] == 4
    again = pickle.loads(pickle.dumps(second.times))
    assert again.seconds == second.times.seconds and again.scans == second.times.scans


def test_each_scan_gets_a_prediction_or_its_named_failure_in_order(tree, small_weights, scan):
    """The contract every runner builds on: an unreadable scan keeps its reason, a network that
    fails on a loaded batch names each readable scan, and in-memory scans that cannot be
    projected keep theirs while the network's own errors propagate."""
    predictor = Predictor.from_checkpoint(small_weights, height=32, width=256, device="cpu")
    (velodyne_dir(tree, "08", layout=KITTI_LAYOUT) / "000001.bin").write_bytes(b"\x01" * 30)
    entries = list_scans(tree, ["08"], layout=KITTI_LAYOUT)
    loaded = load_batch(
        entries, predictor.projection_config, StageTimes(), record=predictor.profile.points
    )
    found = predict_loaded(predictor, loaded)
    assert [isinstance(f, str) for f in found] == [False, True, False]
    assert "000001.bin" in found[1] and "multiple of 16" in found[1]
    alone = predictor.predict(read_scan(entries[2].scan_path))
    np.testing.assert_array_equal(found[2].labels, alone.labels)

    projected = project_scans([scan[::7], scan[:, :3]], predictor.projection_config, StageTimes())
    in_memory = predictor.label_projections(projected)
    assert in_memory[1] == "points must have shape (N, 4), got (123389, 3)"
    np.testing.assert_array_equal(in_memory[0].labels, predictor.predict(scan[::7]).labels)

    def out_of_memory(*args, **kwargs):
        raise RuntimeError("CUDA out of memory")

    predictor.logits = out_of_memory
    failed = "the network failed: CUDA out of memory"
    assert predict_loaded(predictor, loaded) == [failed, found[1], failed]
    with pytest.raises(RuntimeError, match="out of memory"):
        predictor.label_projections(projected)


def test_a_run_summary_tallies_every_scan_and_names_each_failure():
    summary = RunSummary(total=4, skipped=1, seconds=2.0)
    summary.add("08/000000", None, 1200)
    summary.add("08/000001", "unreadable")
    summary.add("08/000002", None, 800)
    assert summary.done == 3 and summary.written == 2 and summary.points == 2000
    assert not summary.ok and summary.failed == {"08/000001": "unreadable"}
    assert summary.lines() == [
        "4 scans: 2 written, 1 already done, 1 failed; 2,000 points in 2.0 s (1.00 scans/s)",
        "FAILED 08/000001: unreadable",
    ]
    assert summary.text() == "\n".join(summary.lines())
    assert batches(list(range(5)), 2) == [[0, 1], [2, 3], [4]]
    with pytest.raises(ValueError, match="--batch-size must be at least 1, got 0"):
        batches([1], 0)
