"""Logits to point classes, the step that `Predictor` and the trainer's validation share."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import data_path

from rangeret.point_labels import DEFAULT_KNN, KnnSettings, point_classes


@pytest.fixture(scope="module")
def scan() -> dict[str, torch.Tensor]:
    """The real scan's projection with a noisy per-pixel argmax and the published kNN output."""
    with np.load(data_path("knn-semantickitti-scan.npz")) as data:
        return {name: torch.from_numpy(data[name]) for name in data.files}


def _classes(scan, knn):
    return point_classes(
        scan["proj_argmax"],
        scan["proj_x"],
        scan["proj_y"],
        scan["proj_range"],
        scan["unproj_range"],
        knn,
        20,
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


def test_the_cpu_thread_count_is_restored(scan):
    threads = torch.get_num_threads()
    _classes(scan, DEFAULT_KNN)
    assert torch.get_num_threads() == threads


def test_predictor_labels_go_through_this_step(monkeypatch, real_scan_path):
    from rangeret import inference
    from rangeret.io import read_scan
    from rangeret.models import build_model
    from rangeret.profiles import load_profile

    calls = []

    def recording(*args, **kwargs):
        calls.append(args[-2])
        return point_classes(*args, **kwargs)

    monkeypatch.setattr(inference, "point_classes", recording)
    torch.manual_seed(0)
    network = build_model("rangeret-cir", 32, 256, layers=1)
    for knn in (None, DEFAULT_KNN):
        profile = load_profile().with_overrides(height=32, width=256)
        predictor = inference.Predictor(network, profile, device="cpu", knn=knn)
        result = predictor.predict(read_scan(real_scan_path))
        assert result.classes.shape == (123_389,)
    assert calls == [None, DEFAULT_KNN]
