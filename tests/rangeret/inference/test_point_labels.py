"""Logits to point classes, the step that `Predictor` and the trainer's validation share."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from rangeret.inference.point_labels import pixel_classes, point_classes_batch
from rangeret.inference.settings import DEFAULT_KNN, KnnSettings
from tests.support.host_syncs import SYNCS_PER_BATCH, host_syncs
from tests.support.paths import data_path


@pytest.fixture(scope="module")
def scan() -> dict[str, torch.Tensor]:
    """The real scan's projection with a noisy per-pixel argmax and the published kNN output."""
    with np.load(data_path("knn-semantickitti-scan.npz")) as data:
        return {name: torch.from_numpy(data[name]) for name in data.files}


def _classes(scan, knn, **rule):
    """One scan's classes: a batch of one."""
    return point_classes_batch(
        scan["proj_argmax"][None],
        [scan["proj_x"]],
        [scan["proj_y"]],
        [scan["proj_range"]],
        [scan["unproj_range"]],
        knn,
        20,
        **rule,
    )


def test_knn_gives_the_published_output(scan):
    classes = _classes(scan, DEFAULT_KNN)
    assert classes.dtype == torch.int64
    np.testing.assert_array_equal(classes.numpy(), scan["expected_knn7_search7"].numpy())
    five = _classes(scan, KnnSettings(k=5, search=5))
    np.testing.assert_array_equal(five.numpy(), scan["expected_knn5_search5"].numpy())


def test_without_knn_each_point_takes_its_pixel(scan):
    classes = _classes(scan, None).numpy()
    x, y, argmax = (scan[k].numpy() for k in ("proj_x", "proj_y", "proj_argmax"))
    valid = x >= 0
    np.testing.assert_array_equal(classes[valid], argmax[y[valid], x[valid]])
    assert (classes[~valid] == 0).all()


def test_points_without_a_pixel_get_class_zero_either_way(scan):
    dropped = dict(scan)
    dropped["proj_x"] = scan["proj_x"].clone()
    dropped["proj_x"][:100] = -1
    for knn in (None, DEFAULT_KNN):
        assert (_classes(dropped, knn)[:100] == 0).all()


def test_without_knn_a_batchs_points_take_their_pixels():
    rng = np.random.default_rng(20)
    sizes = [300, 0, 120]
    argmax = torch.from_numpy(rng.integers(0, 5, (3, 6, 20)))
    proj_x = [np.where(rng.random(n) < 0.05, -1, rng.integers(0, 20, n)) for n in sizes]
    proj_y = [np.where(x < 0, -1, rng.integers(0, 6, len(x))) for x in proj_x]
    proj_range = [np.ones((6, 20), dtype=np.float32)] * 3
    unproj_range = [np.ones(n, dtype=np.float32) for n in sizes]
    parts = (proj_x, proj_y, proj_range, unproj_range)
    result = point_classes_batch(argmax, *parts, None, 5, unlabeled=3)
    expected = [
        np.where(x >= 0, argmax[b].numpy()[y, x], 3)
        for b, (x, y) in enumerate(zip(proj_x, proj_y, strict=True))
    ]
    assert result.dtype == torch.int64
    assert np.array_equal(result.numpy(), np.concatenate(expected))


@pytest.mark.parametrize("knn", [None, DEFAULT_KNN])
def test_a_batch_waits_on_the_host_once(scan, knn):
    """Projection arrays as numpy arrays, the argmax a tensor: only the caller's read waits."""
    fields = ("proj_x", "proj_y", "proj_range", "unproj_range")
    parts = [[scan[f].numpy()] * 3 for f in fields]
    argmax = torch.stack([scan["proj_argmax"]] * 3)
    with host_syncs() as counts:
        result = point_classes_batch(argmax, *parts, knn, 20).cpu()
    assert counts == {"cpu": 1} and sum(counts.values()) == SYNCS_PER_BATCH
    assert torch.equal(result, torch.cat([_classes(scan, knn)] * 3))


def test_the_cpu_thread_count_is_restored(scan):
    threads = torch.get_num_threads()
    _classes(scan, DEFAULT_KNN)
    assert torch.get_num_threads() == threads


@pytest.mark.parametrize("knn", [None, DEFAULT_KNN])
def test_a_batch_gives_each_scans_classes(scan, knn):
    dropped = dict(scan, proj_x=scan["proj_x"].clone())
    dropped["proj_x"][::30] = -1
    flipped = dict(scan, proj_argmax=scan["proj_argmax"].flip(1))
    scans = [scan, dropped, flipped]
    fields = ("proj_x", "proj_y", "proj_range", "unproj_range")
    for as_numpy in (True, False):
        parts = [[s[f].numpy() if as_numpy else s[f] for s in scans] for f in fields]
        argmax = torch.stack([s["proj_argmax"] for s in scans])
        rule = {"votes_from": 0, "unlabeled": 19}
        result = point_classes_batch(argmax, *parts, knn, 20, **rule)
        expected = [_classes(s, knn, **rule) for s in scans]
        assert result.dtype == torch.int64
        assert torch.equal(result, torch.cat(expected))


def _predictor(knn):
    from rangeret.dataset.profiles import load_profile
    from rangeret.inference import predictor as inference
    from rangeret.inference.spec import InferenceSpec
    from rangeret.models import build_model

    torch.manual_seed(0)
    network = build_model("rangeret-cir", 32, 256, layers=1)
    profile = load_profile().with_overrides(height=32, width=256)
    spec = InferenceSpec(device="cpu")
    return inference.Predictor.from_network(network, profile, spec).with_knn(knn)


def test_predictor_labels_go_through_this_step(monkeypatch, real_scan_path):
    from rangeret.inference import predictor as inference
    from rangeret.io.scans import read_scan

    calls = []

    def recording(*args, **kwargs):
        calls.append((len(args[1]), args[-2]))
        return point_classes_batch(*args, **kwargs)

    monkeypatch.setattr(inference, "point_classes_batch", recording)
    points = read_scan(real_scan_path)
    for knn in (None, DEFAULT_KNN):
        predictor = _predictor(knn)
        result = predictor.predict(points)
        assert result.classes.shape == (123_389,)
        batch = predictor.label_projections(
            [predictor.project(p) for p in (points, points[::2], points)]
        )
        assert [len(r.classes) for r in batch] == [123_389, 61_695, 123_389]
        assert np.array_equal(batch[0].classes, result.classes)
        assert np.array_equal(batch[1].classes, predictor.predict(points[::2]).classes)
    assert calls == [(scans, knn) for knn in (None, DEFAULT_KNN) for scans in (1, 3, 1)]


@pytest.mark.parametrize("knn", [None, DEFAULT_KNN])
def test_a_predictor_batch_waits_on_the_host_a_fixed_number_of_times(real_scan_path, knn):
    """`Predictor.refine_batch` as `Predictor.label` runs it: per batch, not per scan or chunk."""
    from rangeret.io.scans import read_scan

    predictor = _predictor(knn)
    points = read_scan(real_scan_path)
    projections = [predictor.project(p) for p in (points, points[::3], points[1::2])]
    logits = predictor.logits(projections)
    expected = [
        predictor.refine_batch([p], out[None])[0]
        for p, out in zip(projections, logits, strict=True)
    ]
    with host_syncs() as counts:
        classes = predictor.refine_batch(projections, logits)
    assert sum(counts.values()) <= SYNCS_PER_BATCH
    for got, want in zip(classes, expected, strict=True):
        assert np.array_equal(got, want)


@pytest.mark.parametrize("first", [0, 1, 3])
def test_pixel_classes_are_torchs_argmax_ties_and_nans_included(first):
    rng = np.random.default_rng(first)
    logits = torch.from_numpy(rng.integers(-3, 4, (2, 7, 5, 33)).astype(np.float32))  # ties
    logits[0, 4, 2, 7] = float("nan")
    logits[1, :, 3, 3] = float("nan")
    logits[1, 5, 0, 0] = float("inf")
    expected = logits[:, first:].argmax(dim=1) + first
    got = pixel_classes(logits, first)
    assert got.dtype == torch.int64 and got.shape == (2, 5, 33)
    assert torch.equal(got, expected)
    if first <= 4:
        assert got[0, 2, 7] == 4  # a NaN is the maximum, as torch.argmax has it
